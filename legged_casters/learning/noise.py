"""Exploration noise that is correlated in time.

On casters the exploration noise itself propels and turns the robot: white noise on
the joint targets, drawn anew every control step, is a fast leg oscillation, and the
casters rectify oscillation into motion (docs/tasks.md: the stochastic actor turns
where the deterministic one does not, and lowering the std takes the turn away).
`CorrelatedGaussianDistribution` draws the noise from a first-order autoregressive
process instead,

    eps_t = rho * eps_(t-1) + sqrt(1 - rho^2) * n_t,    n_t ~ N(0, 1),
    action_t = mean_t + std * eps_t,

whose marginal is the same N(mean, std) as rsl_rl's GaussianDistribution (so PPO's
log-probabilities, entropy and KL are unchanged) but whose power sits below about
(1 - rho) / (2 pi dt) Hz: slow offsets of the legs, which explore posture and tilt,
rather than a shake that skates by itself. rho 0 is white noise. (Eberhard et al.,
ICLR 2023, "Pink Noise Is All You Need", and Korenkevych et al., IJCAI 2019,
"Autoregressive Policies for Continuous Control Deep Reinforcement Learning", use
temporally correlated exploration the same way.)

The process advances only for samples drawn without gradients (the rollout, and
`scripts/evaluate.py --stochastic`): PPO's update also calls sample() on its
mini-batches, with gradients on, and those draws are discarded; they get white noise
and leave the process alone. A batch of another size restarts the process from its
stationary distribution. The state is not a parameter: checkpoints and exports are the
same as with GaussianDistribution.
"""

from __future__ import annotations

import math

import torch
from rsl_rl.modules.distribution import GaussianDistribution


class CorrelatedGaussianDistribution(GaussianDistribution):
    """rsl_rl's GaussianDistribution whose samples follow an AR(1) process per action dimension."""

    def __init__(self, output_dim: int, correlation: float = 0.0, **kwargs) -> None:
        super().__init__(output_dim, **kwargs)
        if not 0.0 <= correlation < 1.0:
            raise ValueError(f"the noise correlation must lie in [0, 1), got {correlation}")
        self.correlation = float(correlation)
        self._eps: torch.Tensor | None = None

    def sample(self) -> torch.Tensor:
        if torch.is_grad_enabled() or self.correlation == 0.0:  # PPO's mini-batches, or white noise
            return super().sample()
        dist = self._distribution
        if dist is None:
            raise RuntimeError("sample() before update(): the distribution has no mean yet")
        fresh = torch.randn_like(dist.mean)
        prev, rho = self._eps, self.correlation
        same = prev is not None and prev.shape == fresh.shape
        self._eps = rho * prev + math.sqrt(1.0 - rho * rho) * fresh if same else fresh
        return dist.mean + dist.stddev * self._eps
