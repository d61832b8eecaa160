"""The driving-wheel robot's feedforward inside the actor: wheel rates from the command.

Each wheel turns at the rate that rolls its contact point at the trunk's commanded
velocity, as a skid-steered vehicle would without slip: omega_i = (vx - wz y_i) / R,
with y_i the wheel's lateral distance from the trunk centre. The legs get no
feedforward. PPO learns the residual (slip in turns, balance, leg motion), as it does
around the caster robot's gait prior (legged_casters/envs/gait.py).
"""

from __future__ import annotations

import torch

from legged_casters.robot import go2


def wheel_lateral_positions() -> list[float]:
    """y (m) of each driving wheel's mid-plane in the trunk frame, go2.LEGS order."""
    y = go2.HIP_OFFSET[1] + go2.THIGH_OFFSET[1] + go2.DRIVE_WHEEL_OFFSET
    return [go2.leg_signs(leg)[1] * y for leg in go2.LEGS]


class DrivePrior(torch.nn.Module):
    """Raw policy observation (n, dim) -> prior action (n, num_actions) in action units:
    zeros for the legs, (vx - wz y_i) / (R * velocity_action_scale) for the wheels.
    `slices` gives (start, scale) of the commands term; the velocity estimate is not
    used (the same call as the gait prior's). Scriptable."""

    def __init__(self, cfg: dict, slices: dict[str, list[float]], action_scale: float):
        super().__init__()
        self.cmd_start, self.cmd_scale = int(slices["commands"][0]), float(slices["commands"][1])
        self.num_legs = int(cfg["num_leg_joints"])
        self.needs_velocity = False
        self.gain = float(cfg.get("gain", 1.0)) / (float(cfg["wheel_radius"]) * float(action_scale))
        self.register_buffer("wheel_y", torch.tensor(cfg["wheel_y"], dtype=torch.float32), persistent=False)

    def forward(self, obs: torch.Tensor, velocity: torch.Tensor) -> torch.Tensor:
        commands = obs[:, self.cmd_start : self.cmd_start + 3] / self.cmd_scale
        wheels = (commands[:, 0:1] - commands[:, 2:3] * self.wheel_y) * self.gain
        legs = torch.zeros(obs.shape[0], self.num_legs, dtype=obs.dtype, device=obs.device)
        return torch.cat([legs, wheels], dim=1)

    @torch.jit.export
    def stop(self, obs: torch.Tensor, mean: torch.Tensor, velocity: torch.Tensor) -> torch.Tensor:
        """The actor's mean unchanged: the wheel robot has no stop pose (GaitPrior.stop's call)."""
        return mean
