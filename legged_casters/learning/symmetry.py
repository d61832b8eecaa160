"""Left-right mirror symmetry for PPO (rsl_rl's symmetry extension, Mittal et al., ICRA 2024,
"Symmetry Considerations for Learning Task Symmetric Robot Policies").

The Go2 and its casters are mirror images of themselves across the trunk's sagittal (x-z)
plane (tests/test_symmetry.py checks every joint of the three robots), and so is each task:
a robot told to turn left should do what its mirror image does when told to turn right.
A policy trained without that knowledge need not: four caster_omni runs (research/log.md,
"Left-right mirror symmetry") turned right at 0.6-0.7 rad/s and left at 0.1-0.4 under the
same 0.8 rad/s command.

`train.symmetry.mode` switches it on:
* "loss": an extra loss, `mirror_loss_coeff` x the mean squared difference between the
  actor's mean action for the mirrored observation and the mirror of its mean action for
  the observation itself (only the actor's observation group has to be mirrorable);
* "augment": every PPO mini-batch also holds the mirror image of each sample (observation
  and action, with the same advantage and return), for the actor and the critic alike;
* "both";
* "log": the mirror loss is only measured (Loss/symmetry in TensorBoard), e.g. for a control
  run beside one that learns from it.

The maps come from the env: `env.action_mirror()` and `env.mirror_maps()` (per observation
group, built from `observation_mirror()`'s per-term maps, which read go2.mirror_joint and
go2.mirror_legs). A group without a map (a term in the world frame) is passed on unmirrored:
with "loss" only the actor's group is read, and the train config refuses "augment" for a
task whose critic observation has no map.
"""

from __future__ import annotations

import torch
from tensordict import TensorDict

MIRROR_FUNCTION = "legged_casters.learning.symmetry:mirror_batch"
"""What the algorithm's symmetry_cfg names as its data_augmentation_func."""


def _maps(env) -> tuple[dict, tuple[torch.Tensor, torch.Tensor]]:
    cached = getattr(env, "_mirror_cache", None)
    if cached is None:
        index, sign = env.action_mirror()
        action = (torch.tensor(index, device=env.device), torch.tensor(sign, device=env.device))
        cached = env._mirror_cache = (env.mirror_maps(), action)
    return cached


def mirror(x: torch.Tensor, index: torch.Tensor, sign: torch.Tensor) -> torch.Tensor:
    """x's mirror image: column k is sign[k] * x[:, index[k]]."""
    return x[:, index] * sign.to(x.dtype)


def with_mirror_image(x: torch.Tensor, index: torch.Tensor, sign: torch.Tensor) -> torch.Tensor:
    """(n, d) -> (2n, d): the rows, then their mirror images (symmetry.mode=exact's batch)."""
    return torch.cat([x, mirror(x, index, sign)], dim=0)


def symmetric_mean(out: torch.Tensor, index: torch.Tensor, sign: torch.Tensor) -> torch.Tensor:
    """(2n, d) outputs for n inputs followed by their mirror images -> (n, d): each output
    averaged with the mirror image of its partner's (an exactly symmetric function whatever
    produced `out`; symmetry.mode=exact)."""
    n = out.shape[0] // 2
    return 0.5 * (out[:n] + mirror(out[n:], index, sign))


def symmetric_pair(out: torch.Tensor, index: torch.Tensor, sign: torch.Tensor) -> torch.Tensor:
    """(2n, d) -> (2n, d): symmetric_mean's n rows, then their mirror images (the mirrored
    actor's velocity estimate for its batch of observations and their mirror images)."""
    return with_mirror_image(symmetric_mean(out, index, sign), index, sign)


def mirror_observation(env, obs: TensorDict) -> TensorDict:
    """obs's mirror image, group by group; a group without a map is passed on unmirrored."""
    groups, _ = _maps(env)
    mirrored = {k: mirror(v, *groups[k]) if groups.get(k) is not None else v for k, v in obs.items()}
    return TensorDict(mirrored, batch_size=obs.batch_size, device=obs.device)


def mirror_action(env, actions: torch.Tensor) -> torch.Tensor:
    """actions' mirror image (env.action_mirror)."""
    return mirror(actions, *_maps(env)[1])


def mirror_batch(
    env, obs: TensorDict | None = None, actions: torch.Tensor | None = None
) -> tuple[TensorDict | None, torch.Tensor | None]:
    """rsl_rl's data augmentation function: (obs, actions) -> each with its mirror image
    appended along the batch dimension (originals first); None stays None."""
    out_obs = None if obs is None else torch.cat([obs, mirror_observation(env, obs)], dim=0)
    out_actions = None if actions is None else torch.cat([actions, mirror_action(env, actions)], dim=0)
    return out_obs, out_actions
