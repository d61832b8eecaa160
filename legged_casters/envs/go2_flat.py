"""go2_flat: the point-foot Go2 trotting on flat ground (the paper's comparison robot).

Standard velocity tracking with a legged_gym-style trotting reward set. It is the
known-learnable task that tells us the stack trains at all, and the baseline for
the caster robot's cost of transport.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

import torch

from legged_casters.envs.base import LeggedEnv
from legged_casters.envs.config import CommandRanges, CommandsCfg, LeggedEnvCfg, RewardsCfg, TerminationCfg
from legged_casters.robot import go2
from legged_casters.train_config import TrainCfg

FEET_SENSORS = tuple(f"{leg}_foot_contact" for leg in go2.LEGS)


def _go2_flat_rewards() -> RewardsCfg:
    return RewardsCfg(
        scales={
            "tracking_lin_vel": 1.0,
            "tracking_ang_vel": 0.5,
            "lin_vel_z": -2.0,
            "ang_vel_xy": -0.05,
            "orientation": -1.0,
            "base_height": -10.0,
            "torques": -2e-4,
            "joint_acc": -2.5e-7,
            "action_rate": -0.01,
            "feet_air_time": 1.0,
            "collision": -1.0,
            "joint_pos_limits": -10.0,
            "termination": 0.0,
        },
        base_height_target=0.30,
        # As in legged_gym: while the penalties outweigh the rewards, a negative total
        # would teach the policy to end episodes early (falling is not penalised).
        only_positive_rewards=True,
    )


@dataclass
class Go2FlatCfg(LeggedEnvCfg):
    robot: Literal["caster", "point", "wheel"] = "point"
    commands: CommandsCfg = field(
        default_factory=lambda: CommandsCfg(ranges=CommandRanges((-1.0, 1.0), (-0.5, 0.5), (-1.0, 1.0)))
    )
    rewards: RewardsCfg = field(default_factory=_go2_flat_rewards)
    # A flipped Go2 can rest on its folded legs without its trunk touching the floor.
    termination: TerminationCfg = field(default_factory=lambda: TerminationCfg(max_tilt_deg=70.0))
    feet_air_time_target: float = field(default=0.5, metadata={"min": 0.0})


class Go2FlatEnv(LeggedEnv):
    # The actor sees the trunk's linear velocity, as in legged_gym's flat-ground
    # baseline (a simulation benchmark, not a deployable estimator-free policy).
    OBSERVATIONS = {
        "policy": ("base_lin_vel", "ang_vel", "projected_gravity", "commands", "joint_pos", "joint_vel", "actions"),
        "critic": ("base_height", "feet_contact"),
    }
    COLLISION_SENSORS = tuple(f"{leg}_{part}_contact" for leg in go2.LEGS for part in ("thigh", "calf"))

    cfg: Go2FlatCfg

    def _init_task_buffers(self) -> None:
        self.feet_air_time = torch.zeros(self.num_envs, 4, device=self.device)
        self.last_contacts = torch.zeros(self.num_envs, 4, dtype=torch.bool, device=self.device)
        self.first_contact = torch.zeros_like(self.last_contacts)
        self.air_time_at_touchdown = torch.zeros_like(self.feet_air_time)

    def _reset_task_state(self, env_ids: torch.Tensor) -> None:
        self.feet_air_time[env_ids] = 0.0
        self.last_contacts[env_ids] = False

    def _post_physics_step(self) -> None:
        contact = self.contact_found(FEET_SENSORS)
        touching = contact | self.last_contacts  # MuJoCo contacts can flicker for a step
        self.last_contacts = contact
        self.feet_air_time += self.dt
        self.first_contact = (self.feet_air_time > self.dt) & touching
        self.air_time_at_touchdown = self.feet_air_time * self.first_contact
        self.feet_air_time *= ~touching

    def _obs_feet_contact(self) -> torch.Tensor:
        return self.contact_found(FEET_SENSORS).float()

    def _reward_feet_air_time(self) -> torch.Tensor:
        """Reward steps longer than the target air time, paid at touchdown, while moving."""
        target = self.cfg.feet_air_time_target
        reward = torch.sum((self.air_time_at_touchdown - target) * self.first_contact, dim=1)
        return reward * (torch.linalg.norm(self.commands[:, :2], dim=1) > 0.1)


def go2_flat_train_cfg() -> TrainCfg:
    return TrainCfg(experiment_name="go2_flat", max_iterations=1500)
