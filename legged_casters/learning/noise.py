"""Exploration noise that is correlated in time, or absent for a share of the envs.

On casters the exploration noise itself propels and turns the robot: white noise on
the joint targets, drawn anew every control step, is a fast leg oscillation, and the
casters rectify oscillation into motion (research/log.md: the stochastic actor turns
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

A share of the envs can also act without any exploration noise (`quiet_fraction`, config
`policy.noise_free_fraction`): the last rows of each rollout batch take the mean action,
as the deployed actor does. On casters the deterministic actor can do something the noisy
one never shows (stand still under a small command that the noise would have skated), and
the velocity estimator, trained on the rollout, only learns what the rollout shows
(research/log.md, "Why it stands under +0.25 m/s"). For PPO these rows cost nothing but
their share of the batch: at a = mean the log-probability's gradient with respect to the
mean is zero, and the critic learns their returns as any others.

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
    """rsl_rl's GaussianDistribution whose rollout samples follow an AR(1) process per action
    dimension, with the last `quiet_fraction` of the batch's rows at the mean."""

    def __init__(self, output_dim: int, correlation: float = 0.0, quiet_fraction: float = 0.0, **kwargs) -> None:
        super().__init__(output_dim, **kwargs)
        if not 0.0 <= correlation < 1.0:
            raise ValueError(f"the noise correlation must lie in [0, 1), got {correlation}")
        if not 0.0 <= quiet_fraction < 1.0:
            raise ValueError(f"the noise-free fraction must lie in [0, 1), got {quiet_fraction}")
        self.correlation = float(correlation)
        self.quiet_fraction = float(quiet_fraction)
        self._eps: torch.Tensor | None = None

    def sample(self) -> torch.Tensor:
        if torch.is_grad_enabled() or (self.correlation == 0.0 and self.quiet_fraction == 0.0):
            return super().sample()  # PPO's mini-batches, or plain white noise
        dist = self._distribution
        if dist is None:
            raise RuntimeError("sample() before update(): the distribution has no mean yet")
        eps = torch.randn_like(dist.mean)
        if self.correlation > 0.0:
            prev, rho = self._eps, self.correlation
            same = prev is not None and prev.shape == eps.shape
            eps = self._eps = rho * prev + math.sqrt(1.0 - rho * rho) * eps if same else eps
        quiet = int(round(self.quiet_fraction * eps.shape[0]))
        if quiet:
            eps = torch.cat([eps[: eps.shape[0] - quiet], torch.zeros_like(eps[:quiet])])
        return dist.mean + dist.stddev * eps
