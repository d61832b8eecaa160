"""go2_wheel_flat: the Go2 with actuated driving wheels (the paper's third robot, Table II).

Velocity tracking on flat ground with 16 actions: the 12 leg joints as position
servos and the 4 wheels as velocity servos (`go2.action_layout("wheel")`). The wheels
roll for vx and turn the robot by skid steering for wz; the legs keep the trunk level
and absorb pushes. With fixed, unsteered wheel axles the robot cannot move sideways,
so vy is never commanded (the lateral command range is zero).

The actor sees what a robot measures (IMU, joints, command, last action), no
privileged state, so it deploys through the bridge; the critic also gets the trunk's
linear velocity and height. The actor adds the skid-steer feedforward of
`legged_casters.envs.drive` to its mean and learns the residual.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

import torch

from legged_casters.envs.base import LeggedEnv
from legged_casters.envs.config import (
    CommandRanges,
    CommandsCfg,
    LeggedEnvCfg,
    RewardsCfg,
    SimCfg,
    TerminationCfg,
)
from legged_casters.envs.drive import wheel_lateral_positions
from legged_casters.robot import go2
from legged_casters.train_config import TrainCfg

WHEEL_CONTACTS = tuple(f"{leg}_wheel_contact" for leg in go2.LEGS)


def _wheel_rewards() -> RewardsCfg:
    return RewardsCfg(
        scales={
            "tracking_lin_vel": 1.0,
            "tracking_ang_vel": 1.0,
            "lin_vel_z": -2.0,
            "ang_vel_xy": -0.05,
            "orientation": -2.0,
            "base_height": -10.0,
            "torques": -1e-4,
            "joint_acc": -2.5e-7,
            "action_rate": -0.01,
            "leg_deviation": -0.2,
            "collision": -1.0,
            "joint_pos_limits": -10.0,
            "termination": 0.0,
        },
        tracking_sigma=0.25,
        base_height_target=0.38,
        only_positive_rewards=True,
    )


@dataclass
class Go2WheelFlatCfg(LeggedEnvCfg):
    robot: Literal["caster", "point", "wheel"] = "wheel"
    # 5 ms x 4 = 50 Hz policy, as caster_omni (the wheel contact is checked at 5 ms by
    # tests/test_wheel_robot.py).
    sim: SimCfg = field(default_factory=lambda: SimCfg(timestep=0.005, decimation=4))
    commands: CommandsCfg = field(
        default_factory=lambda: CommandsCfg(
            ranges=CommandRanges((-1.5, 1.5), (0.0, 0.0), (-1.2, 1.2)), single_axis_fraction=0.5
        )
    )
    rewards: RewardsCfg = field(default_factory=_wheel_rewards)
    termination: TerminationCfg = field(default_factory=lambda: TerminationCfg(max_tilt_deg=70.0))
    feedforward: bool = True
    """Add the skid-steer wheel feedforward (legged_casters.envs.drive) to the actor's mean."""


class Go2WheelFlatEnv(LeggedEnv):
    OBSERVATIONS = {
        "policy": ("ang_vel", "projected_gravity", "commands", "joint_pos", "joint_vel", "actions"),
        "critic": ("base_lin_vel", "base_height", "wheel_contact"),
    }
    COLLISION_SENSORS = tuple(f"{leg}_{part}_contact" for leg in go2.LEGS for part in ("thigh", "calf"))

    cfg: Go2WheelFlatCfg

    def actor_prior(self) -> dict | None:
        if not self.cfg.feedforward:
            return None
        slices = self.policy_obs_slices()
        return {
            "kind": "drive",
            "cfg": {
                "wheel_radius": go2.DRIVE_WHEEL_RADIUS,
                "wheel_y": wheel_lateral_positions(),
                "num_leg_joints": self.layout.num_legs_joints,
            },
            "slices": {"commands": slices["commands"]},
            "action_scale": self.cfg.control.velocity_action_scale,
        }

    def _obs_wheel_contact(self) -> torch.Tensor:
        return self.contact_found(WHEEL_CONTACTS).float()

    def _reward_leg_deviation(self) -> torch.Tensor:
        """|q - q0| of the leg joints: the legs hold the stance, the wheels drive."""
        return torch.sum(self._obs_joint_pos().abs(), dim=1)


def go2_wheel_flat_train_cfg() -> TrainCfg:
    cfg = TrainCfg(experiment_name="go2_wheel_flat", max_iterations=600)
    # With std 1.0 a wheel's exploration noise alone is 10 rad/s (0.9 m/s at the rim).
    cfg.policy.init_noise_std = 0.3
    cfg.algorithm.desired_kl = 0.02
    return cfg
