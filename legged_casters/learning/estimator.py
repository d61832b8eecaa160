"""A velocity estimator trained by regression next to PPO (concurrent state estimation).

The actor cannot measure its trunk velocity, yet speed control needs it. Following the
idea of Ji et al. (RA-L 2022, "Concurrent Training of a Control Policy and a State
Estimator"), a small MLP inside the actor regresses the simulator's trunk linear
velocity (trunk frame, m/s) from what the robot measures: the normalised policy
observation, proprioceptive history included. The actor's MLP then reads the estimate
(detached: PPO's gradient never reaches the estimator) beside the current observation.
The estimator is part of the actor, so checkpoints, export (TorchScript / ONNX) and the
deployment bridge carry it without anything new; the robot computes its own estimate.

The regression target comes from the env as its own observation group (`TARGET_GROUP`),
which only the estimator's loss reads. `EstimatorPPO` runs rsl_rl's PPO update, then
`epochs` passes of Adam on the estimator over the same rollout, and reports the loss
(Loss/estimator_mse in TensorBoard) and the estimate's RMS error (Loss/estimator_rms, m/s).
With `estimator_mirror` (train config `symmetry.estimator`) each of those mini-batches also
holds every sample's mirror image (legged_casters.learning.symmetry), so the estimate of
the mirrored state is taught to be the mirrored velocity.
"""

from __future__ import annotations

import torch
from rsl_rl.algorithms import PPO
from rsl_rl.modules import MLP
from rsl_rl.utils.utils import reduce_gradients_in_buckets

from legged_casters.learning.symmetry import mirror_batch

TARGET_GROUP = "estimator_target"
"""Observation group holding the estimator's regression target (base_lin_vel, trunk frame, m/s)."""


class VelocityEstimator(torch.nn.Module):
    """Normalised policy observation (n, obs_dim) -> trunk velocity estimate (n, out_dim).

    `skip`: [start, stop) column ranges of the observation it does not read (e.g. the
    command); None or empty: it reads all of them."""

    def __init__(
        self, obs_dim: int, out_dim: int, hidden_dims: list[int], activation: str = "elu",
        skip: list[list[int]] | None = None,
    ):  # fmt: skip
        super().__init__()
        self.out_dim = int(out_dim)
        keep = torch.ones(obs_dim, dtype=torch.bool)
        for start, stop in skip or ():
            if not 0 <= start < stop <= obs_dim:
                raise ValueError(f"estimator skip columns [{start}, {stop}) outside the {obs_dim} observations")
            keep[start:stop] = False
        # not saved in checkpoints: it follows from the train config, and older runs (no skip) load as before
        self.register_buffer("columns", keep.nonzero().flatten(), persistent=False)
        self.skips = bool(not keep.all())  # without a skip the input goes in as it is (no copy per step)
        self.net = MLP(len(self.columns), out_dim, list(hidden_dims), activation)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.net(x[:, self.columns] if self.skips else x)


class EstimatorPPO(PPO):
    """rsl_rl's PPO plus supervised epochs of the actor's estimator after each update."""

    def __init__(
        self,
        *args,
        estimator_learning_rate: float = 1e-3,
        estimator_epochs: int = 2,
        estimator_mini_batches: int = 4,
        estimator_mirror: bool = False,
        pose_imitation_learning_rate: float = 0.0,
        **kwargs,
    ):
        super().__init__(*args, **kwargs)
        self.estimator_mirror = bool(estimator_mirror)
        self.mirror_env = None
        """The env whose mirror maps estimator_mirror uses (CheckpointingRunner sets it)."""
        estimator = getattr(self._raw_actor, "estimator", None)
        if estimator is None:
            raise ValueError("EstimatorPPO needs an actor with an estimator (policy.estimator_hidden_dims)")
        self.estimator_epochs = int(estimator_epochs)
        self.estimator_mini_batches = int(estimator_mini_batches)
        self.estimator_optimizer = torch.optim.Adam(estimator.parameters(), lr=estimator_learning_rate)
        self.pose_optimizer = None
        if pose_imitation_learning_rate > 0.0:
            if not getattr(getattr(self._raw_actor, "prior", None), "stop_on", False):
                raise ValueError("policy.stop_pose_imitation needs the stop pose (gait.stop_pitch)")
            self.pose_optimizer = torch.optim.Adam(self._raw_actor.mlp.parameters(), lr=pose_imitation_learning_rate)

    def update(self) -> dict[str, float]:
        losses = super().update()  # leaves the rollout in storage (clear() only rewinds its cursor)
        mse = self.update_estimator()
        losses["estimator_mse"] = mse
        losses["estimator_rms"] = (mse * 3.0) ** 0.5  # RMS of the 3-vector error, m/s
        if self.pose_optimizer is not None:
            losses["pose_imitation"] = self.update_pose_imitation()
        return losses

    def _step(self, optimizer: torch.optim.Optimizer, module: torch.nn.Module, loss: torch.Tensor) -> None:
        """One step of `optimizer` on `module`'s weights down `loss`; as PPO's own step, every
        process of a multi-process run applies the averaged gradient."""
        optimizer.zero_grad()
        loss.backward()
        if self.is_multi_gpu:
            reduce_gradients_in_buckets(module.parameters(), self.gpu_world_size, self.grad_reduce_bucket_mb)
        optimizer.step()

    def update_pose_imitation(self) -> float:
        """One pass of Adam over the rollout that pulls the network's own mean towards the
        stop pose's action on the samples where the pose holds (policy.stop_pose_imitation):
        PPO gives the MLP no gradient there (the pose replaces its output), and the actor
        hands back to that output when the command comes. The mean squared gap (action
        units^2) over the posed samples, 0 without any."""
        actor = self._raw_actor
        total, count = 0.0, 0
        for batch in self.storage.mini_batch_generator(self.estimator_mini_batches, 1):
            own, posed = actor.means(batch.observations)
            held = (own != posed).any(dim=1)
            # a batch without a posed sample steps too (a zero gradient): every process of a
            # multi-process run must reach the same gradient reductions
            gap = (own - posed.detach()).pow(2).mean(dim=1)
            loss = (gap * held).sum() / held.sum().clamp(min=1)
            self._step(self.pose_optimizer, actor.mlp, loss)
            if held.any():
                total += loss.item()
                count += 1
        return total / max(count, 1)

    def update_estimator(self) -> float:
        """`estimator_epochs` passes of Adam over the rollout in storage; the mean MSE (m/s)^2."""
        actor = self._raw_actor
        total, count = 0.0, 0
        for batch in self.storage.mini_batch_generator(self.estimator_mini_batches, self.estimator_epochs):
            obs = batch.observations
            if self.estimator_mirror:  # each sample and its mirror image (the target's vy flips with it)
                if self.mirror_env is None:
                    raise RuntimeError("estimator_mirror needs the env's mirror maps: set EstimatorPPO.mirror_env")
                obs, _ = mirror_batch(self.mirror_env, obs)
            loss = torch.nn.functional.mse_loss(actor.estimate(obs), obs[TARGET_GROUP])
            self._step(self.estimator_optimizer, actor.estimator, loss)
            total += loss.item()
            count += 1
        return total / max(count, 1)

    def save(self) -> dict:
        saved = super().save()
        saved["estimator_optimizer_state_dict"] = self.estimator_optimizer.state_dict()
        return saved

    def load(self, loaded_dict: dict, load_cfg: dict | None, strict: bool) -> bool:
        out = super().load(loaded_dict, load_cfg, strict)
        if "estimator_optimizer_state_dict" in loaded_dict and (load_cfg is None or load_cfg.get("optimizer")):
            self.estimator_optimizer.load_state_dict(loaded_dict["estimator_optimizer_state_dict"])
        return out
