"""Actor models beyond rsl_rl's own: an MLP whose mean adds a fixed trajectory prior,
optionally fed by a velocity estimator.

`PriorMLPModel` is rsl_rl's MLPModel with one change: a prior computed from the raw
policy observation (the caster robot's skating prior `legged_casters.envs.gait.GaitPrior`
or the wheel robot's drive feedforward `legged_casters.envs.drive.DrivePrior`) is
added to the MLP output before the Gaussian head. PPO therefore learns a residual
around the prior, its exploration noise is centred on the prior's motion, and the
deterministic actor (and its export) is prior + MLP: the robot side runs one network.

With `estimator` (legged_casters.learning.estimator), the MLP reads the estimator's
trunk-velocity estimate (detached) beside the normalised observation, and so does the
prior (a caster prior with speed feedback pushes for the error between the command and
that estimate; it needs the estimator); with
`actor_history: False` it reads only the current observation's terms (the estimator
alone reads the proprioceptive history), which also makes the actor small.

With `mirror` (train config `symmetry.mode=exact`) the actor is left-right symmetric by
construction: its mean is the average of what the network gives for the observation and
the mirror image of what it gives for the mirrored observation, and the velocity estimate
likewise (the mirror maps of legged_casters.learning.symmetry). The mirrored actor's mean
for the mirrored observation is then exactly the mirror of its mean, whatever the weights:
a robot told to go straight has no side to drift to. Both halves go through the network
in one batch of twice the rows; the export (legged_casters.tools.export) does the same.
"""

from __future__ import annotations

import torch
from rsl_rl.models import MLPModel
from rsl_rl.utils import unpad_trajectories
from tensordict import TensorDict

from legged_casters.envs.drive import DrivePrior
from legged_casters.envs.gait import GaitPrior
from legged_casters.learning.estimator import VelocityEstimator
from legged_casters.learning.symmetry import symmetric_mean, symmetric_pair, with_mirror_image

MIRRORED = ("observation", "action", "estimate")
"""The maps of the actor's `mirror` dict: [index, sign] each (symmetry.mirror's convention)."""

PRIORS = {"gait": GaitPrior, "drive": DrivePrior}
"""prior["kind"] -> module; a prior without a kind is the caster gait prior (older runs)."""


def make_prior(prior: dict) -> torch.nn.Module:
    kind = prior.get("kind", "gait")
    if kind not in PRIORS:
        raise ValueError(f"unknown actor prior kind {kind!r}; expected one of {sorted(PRIORS)}")
    return PRIORS[kind](prior["cfg"], prior["slices"], prior["action_scale"])


def kept_columns(dim: int, drop: tuple[int, int] | None) -> torch.Tensor:
    """Indices 0..dim-1 without the range [start, stop) of `drop` (all of them for None)."""
    keep = torch.ones(dim, dtype=torch.bool)
    if drop is not None:
        keep[drop[0] : drop[1]] = False
    return keep.nonzero().flatten()


class ColumnsMLPModel(MLPModel):
    """rsl_rl's MLPModel whose MLP skips the observation columns [start, stop) of `drop`
    (e.g. a critic that has the privileged state and no use for the actor's history)."""

    def __init__(self, obs: TensorDict, obs_groups, obs_set: str, output_dim: int, drop: list[int], **kwargs):
        self._drop = (int(drop[0]), int(drop[1]))
        super().__init__(obs, obs_groups, obs_set, output_dim, **kwargs)
        self.register_buffer("mlp_columns", self._mlp_columns(), persistent=False)

    def _mlp_columns(self) -> torch.Tensor:
        return kept_columns(self.obs_dim, self._drop)

    def _get_latent_dim(self) -> int:
        return len(self._mlp_columns())

    def get_latent(self, obs: TensorDict, masks=None, hidden_state=None) -> torch.Tensor:
        return super().get_latent(obs, masks, hidden_state)[:, self.mlp_columns]


class PriorMLPModel(MLPModel):
    """rsl_rl's MLPModel + a prior added to the mean (+ an optional velocity estimator).

    `estimator`: {"hidden_dims": [...], "out_dim": 3, "actor_history": bool,
    "history_slice": [start, stop]} (the proprio_history term's columns in the policy
    observation; the MLP skips them when actor_history is false).
    `mirror`: {"observation": [index, sign], "action": [...], "estimate": [...]} (the last
    only with an estimator): the actor is made exactly left-right symmetric."""

    def __init__(
        self, obs: TensorDict, obs_groups, obs_set: str, output_dim: int, prior: dict, estimator: dict | None = None,
        mirror: dict | None = None, **kwargs,
    ):  # fmt: skip
        self._estimator_cfg = estimator
        super().__init__(obs, obs_groups, obs_set, output_dim, **kwargs)
        self.mirrored = mirror is not None
        if mirror is not None:
            self._register_mirror(mirror, output_dim, estimator)
        if self.distribution is not None and self.distribution.input_dim != output_dim:
            raise ValueError(
                f"{type(self).__name__} adds the prior to the distribution's mean: it needs a distribution whose "
                f"input is the {output_dim} action means (e.g. rsl_rl's GaussianDistribution), got "
                f"{type(self.distribution).__name__} with input {self.distribution.input_dim}"
            )
        self.prior = make_prior(prior)
        if self.prior.needs_velocity and estimator is None:
            raise ValueError(
                "the actor's prior has speed feedback (gait.speed_feedback > 0) and needs the velocity estimator: "
                "set policy.estimator_hidden_dims (or gait.speed_feedback=0)"
            )
        self.estimator = None
        if estimator is not None:
            out_dim, activation = int(estimator.get("out_dim", 3)), kwargs.get("activation", "elu")
            self.estimator = VelocityEstimator(
                self.obs_dim, out_dim, estimator["hidden_dims"], activation, estimator.get("skip_slices")
            )
            self.register_buffer("mlp_columns", self._mlp_columns(), persistent=False)

    def _register_mirror(self, maps: dict, output_dim: int, estimator: dict | None) -> None:
        """The mirror maps as buffers <name>_mirror_index / _sign (not saved: they follow from the
        env, and a checkpoint trained without them loads into a mirrored actor unchanged)."""
        dims = {"observation": self.obs_dim, "action": output_dim}
        if estimator is not None:
            dims["estimate"] = int(estimator.get("out_dim", 3))
        for name, dim in dims.items():  # names of MIRRORED, the maps the export copies
            if name not in maps:
                raise ValueError(f"the mirrored actor needs the {name!r} mirror map; got {sorted(maps)}")
            index, sign = maps[name]
            if sorted(index) != list(range(dim)) or len(sign) != dim:
                raise ValueError(f"the {name!r} mirror map must permute its {dim} columns, got {len(index)}")
            self.register_buffer(f"{name}_mirror_index", torch.as_tensor(index, dtype=torch.long), persistent=False)
            self.register_buffer(f"{name}_mirror_sign", torch.as_tensor(sign, dtype=torch.float), persistent=False)

    def _map(self, name: str) -> tuple[torch.Tensor, torch.Tensor]:
        return getattr(self, f"{name}_mirror_index"), getattr(self, f"{name}_mirror_sign")

    def _mlp_columns(self) -> torch.Tensor:
        """Columns of the normalised observation the MLP reads (all unless the history is left to the estimator)."""
        cfg = self._estimator_cfg
        skip_history = cfg is not None and not cfg.get("actor_history", True)
        return kept_columns(self.obs_dim, tuple(cfg["history_slice"]) if skip_history else None)

    def _get_latent_dim(self) -> int:
        if self._estimator_cfg is None:
            return self.obs_dim
        return len(self._mlp_columns()) + int(self._estimator_cfg.get("out_dim", 3))

    def estimate(self, obs: TensorDict) -> torch.Tensor:
        """The estimator's output (n, out_dim), m/s, from the policy observation groups."""
        raw = torch.cat([obs[group] for group in self.obs_groups], dim=-1)
        if self.mirrored:
            both = with_mirror_image(raw, *self._map("observation"))
            return symmetric_mean(self.estimator(self.obs_normalizer(both)), *self._map("estimate"))
        return self.estimator(self.obs_normalizer(raw))

    def mlp_input(self, normalised: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(the MLP's input, the detached velocity estimate or an (n, 0) tensor without an estimator).
        Mirrored actor: `normalised` is the 2n rows of with_mirror_image, and the estimate of the
        second half is the mirror of the first's symmetric estimate."""
        if self.estimator is None:
            return normalised, normalised[:, :0]
        estimate = self.estimator(normalised).detach()
        if self.mirrored:
            estimate = symmetric_pair(estimate, *self._map("estimate"))
        return torch.cat([normalised[:, self.mlp_columns], estimate], dim=-1), estimate

    def as_jit(self):
        raise NotImplementedError("rsl_rl's JIT export would drop the prior: use export.py (DeployedPolicy)")

    def as_onnx(self, verbose: bool):
        raise NotImplementedError("rsl_rl's ONNX export would drop the prior: use export.py (DeployedPolicy)")

    def means(self, obs: TensorDict) -> tuple[torch.Tensor, torch.Tensor]:
        """(the network's own mean: prior + MLP, symmetrised; the actor's mean: the same with
        the stop pose where it holds, GaitPriorCfg.stop_pitch) for a batch of observations."""
        observed = torch.cat([obs[group] for group in self.obs_groups], dim=-1)
        raw = with_mirror_image(observed, *self._map("observation")) if self.mirrored else observed
        x, estimate = self.mlp_input(self.obs_normalizer(raw))
        own = self.mlp(x) + self.prior(raw, estimate)
        if self.mirrored:
            own = symmetric_mean(own, *self._map("action"))
        # the stop pose under a zero command, where the prior has one (the estimate of the rows observed)
        return own, self.prior.stop(observed, own, estimate[: observed.shape[0]])

    def forward(self, obs: TensorDict, masks=None, hidden_state=None, stochastic_output: bool = False) -> torch.Tensor:
        obs = unpad_trajectories(obs, masks) if masks is not None and not self.is_recurrent else obs
        mean = self.means(obs)[1]
        if self.distribution is not None:
            if stochastic_output:
                self.distribution.update(mean)
                return self.distribution.sample()
            return self.distribution.deterministic_output(mean)
        return mean
