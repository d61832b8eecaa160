"""Actor models beyond rsl_rl's own: an MLP whose mean adds a fixed trajectory prior.

`PriorMLPModel` is rsl_rl's MLPModel with one change: a prior computed from the raw
policy observation (the caster robot's skating prior `legged_casters.envs.gait.GaitPrior`
or the wheel robot's drive feedforward `legged_casters.envs.drive.DrivePrior`) is
added to the MLP output before the Gaussian head. PPO therefore learns a residual
around the prior, its exploration noise is centred on the prior's motion, and the
deterministic actor (and its export) is prior + MLP: the robot side runs one network.
"""

from __future__ import annotations

import torch
from rsl_rl.models import MLPModel
from rsl_rl.utils import unpad_trajectories
from tensordict import TensorDict

from legged_casters.envs.drive import DrivePrior
from legged_casters.envs.gait import GaitPrior

PRIORS = {"gait": GaitPrior, "drive": DrivePrior}
"""prior["kind"] -> module; a prior without a kind is the caster gait prior (older runs)."""


def make_prior(prior: dict) -> torch.nn.Module:
    kind = prior.get("kind", "gait")
    if kind not in PRIORS:
        raise ValueError(f"unknown actor prior kind {kind!r}; expected one of {sorted(PRIORS)}")
    return PRIORS[kind](prior["cfg"], prior["slices"], prior["action_scale"])


class PriorMLPModel(MLPModel):
    def __init__(self, obs: TensorDict, obs_groups, obs_set: str, output_dim: int, prior: dict, **kwargs):
        super().__init__(obs, obs_groups, obs_set, output_dim, **kwargs)
        if self.distribution is not None and self.distribution.input_dim != output_dim:
            raise ValueError(
                f"{type(self).__name__} adds the prior to the distribution's mean: it needs a distribution whose "
                f"input is the {output_dim} action means (e.g. rsl_rl's GaussianDistribution), got "
                f"{type(self.distribution).__name__} with input {self.distribution.input_dim}"
            )
        self.prior = make_prior(prior)

    def as_jit(self):
        raise NotImplementedError("rsl_rl's JIT export would drop the prior: use export.py (DeployedPolicy)")

    def as_onnx(self, verbose: bool):
        raise NotImplementedError("rsl_rl's ONNX export would drop the prior: use export.py (DeployedPolicy)")

    def forward(self, obs: TensorDict, masks=None, hidden_state=None, stochastic_output: bool = False) -> torch.Tensor:
        obs = unpad_trajectories(obs, masks) if masks is not None and not self.is_recurrent else obs
        raw = torch.cat([obs[group] for group in self.obs_groups], dim=-1)
        mean = self.mlp(self.obs_normalizer(raw)) + self.prior(raw)
        if self.distribution is not None:
            if stochastic_output:
                self.distribution.update(mean)
                return self.distribution.sample()
            return self.distribution.deterministic_output(mean)
        return mean
