"""Configuration shared by every legged task (typed dataclasses; see legged_casters.config)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal


@dataclass
class SimCfg:
    backend: Literal["auto", "cpu", "warp"] = "auto"
    """auto: MuJoCo Warp when CUDA is available, else MuJoCo C (rollout thread pool)."""
    decimation: int = field(default=10, metadata={"min": 1})
    """Physics steps per policy step: dt 2 ms x 10 = 50 Hz policy."""
    timestep: float | None = field(default=None, metadata={"min": 1e-4, "max": 0.01})
    """Physics step (s); None keeps the model's (2 ms). MuJoCo raises a contact's solref
    time constant to at least 2 x timestep; the env sets it so explicitly. 5 ms with
    solref 0.01 was measured safe for the caster contact (docs/robot.md)."""
    device: str = "auto"
    """Torch device of the env tensors; auto: cuda:0 for Warp on CUDA, else cpu."""


@dataclass
class ControlCfg:
    action_scale: float = field(default=0.25, metadata={"min": 0.0})
    """Position joints: target = nominal pose + action_scale * action (rad)."""
    velocity_action_scale: float = field(default=10.0, metadata={"min": 0.0})
    """Velocity joints (driving wheels): target = velocity_action_scale * action (rad/s)."""
    clip_actions: float = field(default=100.0, metadata={"min": 0.0})


@dataclass
class CommandRanges:
    lin_vel_x: tuple[float, float] = (-1.0, 1.0)
    lin_vel_y: tuple[float, float] = (-0.5, 0.5)
    ang_vel_yaw: tuple[float, float] = (-1.0, 1.0)


@dataclass
class CommandsCfg:
    resampling_time: float = field(default=10.0, metadata={"min": 0.02})
    standing_fraction: float = field(default=0.1, metadata={"min": 0.0, "max": 1.0})
    """Fraction of resampled commands that are exactly zero (stand still). A zero drawn
    while the robot moves is a stop: the joystick let go, a stop pressed at speed."""
    reverse_fraction: float = field(default=0.0, metadata={"min": 0.0, "max": 1.0})
    """Fraction of resampled commands that instead reverse the planar part of the command
    before it (vx, vy -> -vx, -vy, yaw rate kept): an abrupt reversal from the speed the
    robot has reached."""
    single_axis_fraction: float = field(default=0.0, metadata={"min": 0.0, "max": 1.0})
    """Fraction of resampled commands that keep only one of vx, vy, wz (drawn uniformly),
    so that pure sideways motion and turning on the spot are trained, not only mixtures."""
    ranges: CommandRanges = field(default_factory=CommandRanges)
    curriculum: bool = False
    """Widen lin_vel_x towards `max_lin_vel_x` while tracking is good."""
    max_lin_vel_x: tuple[float, float] = (-1.0, 1.0)
    curriculum_step: float = field(default=0.25, metadata={"min": 0.0})
    curriculum_threshold: float = field(default=0.8, metadata={"min": 0.0, "max": 1.0})
    """Fraction of the maximum tracking an end of the range must earn on average to widen
    (see `curriculum_mode`)."""
    curriculum_mode: Literal["episode", "edge"] = "episode"
    """How the curriculum judges tracking, once per episode length:
    "episode": legged_gym's rule: the linear-tracking term (vx and vy) summed over the
    episodes that ended in that period, divided by the episode length (a robot that fell
    early counts its missing steps as zero); both ends of the vx range widen together.
    "edge": each end of the vx range on its own: the robots whose vx command lies within
    `curriculum_step` of that end and at least `curriculum_step` from zero (a standing
    robot never counts), told to move along x alone (and, on the caster robot, in
    four-wheel mode), scored on vx alone (exp(-(vx - cmd)^2 / tracking_sigma) per step,
    from `curriculum_settle_s` after each new command, the step a robot falls excluded);
    that end widens by `curriculum_step` when their mean is above the threshold."""
    curriculum_settle_s: float = field(default=1.0, metadata={"min": 0.0})
    """"edge" mode: seconds after a new command before a robot's steps count (acceleration);
    shorter than `resampling_time`. (train.py starts the episodes at random lengths, so in
    the first resampling period a robot may count from a stand.)"""

    def limits(self) -> list[tuple[float, float]]:
        """(lo, hi) of vx, vy, wz that training can command: the ranges, vx widened to the
        curriculum's limit where the curriculum is on."""
        r = self.ranges
        vx = tuple(r.lin_vel_x)
        if self.curriculum:
            vx = (min(vx[0], self.max_lin_vel_x[0]), max(vx[1], self.max_lin_vel_x[1]))
        return [vx, tuple(r.lin_vel_y), tuple(r.ang_vel_yaw)]


@dataclass
class InitStateCfg:
    joint_pos_noise: float = field(default=0.1, metadata={"min": 0.0})
    """Uniform noise (rad) on the nominal joint positions at reset."""
    base_vel_noise: float = field(default=0.1, metadata={"min": 0.0})
    random_yaw: bool = True


@dataclass
class NoiseCfg:
    enabled: bool = True
    level: float = field(default=1.0, metadata={"min": 0.0})
    scales: dict[str, float] = field(
        default_factory=lambda: {"ang_vel": 0.2, "projected_gravity": 0.05, "joint_pos": 0.01, "joint_vel": 1.5}
    )
    """Uniform noise amplitude per policy observation term, in the term's own units."""
    bias: dict[str, float] = field(default_factory=dict)
    """Constant offset per policy observation term, in the term's own units, drawn per env
    and per value uniformly in +-value at every reset and added to every observation of
    that episode (an IMU's gyro bias: `ang_vel`; a tilted IMU mount: `projected_gravity`,
    not renormalised). Independent of `enabled` and `level`; empty: none. The history
    records it as the policy observed it."""


@dataclass
class ObservationsCfg:
    scales: dict[str, float] = field(
        default_factory=lambda: {"lin_vel": 2.0, "ang_vel": 0.25, "joint_vel": 0.05, "swivel_vel": 0.05}
    )
    """Multiplier per observation term (terms not listed: 1)."""
    clip: float = field(default=100.0, metadata={"min": 0.0})


@dataclass
class DomainRandCfg:
    """Per-env model parameters, drawn again whenever an env resets."""

    randomize_friction: bool = True
    friction_range: tuple[float, float] = (0.5, 1.25)
    randomize_base_mass: bool = True
    added_mass_range: tuple[float, float] = (-1.0, 1.0)
    randomize_com: bool = True
    com_offset_range: tuple[float, float] = (-0.05, 0.05)
    """Trunk centre-of-mass offset along x, y and z (m)."""
    randomize_gains: bool = True
    kp_scale_range: tuple[float, float] = (0.9, 1.1)
    kd_scale_range: tuple[float, float] = (0.9, 1.1)
    motor_strength_range: tuple[float, float] = (1.0, 1.0)
    """Per env and motor, drawn at reset: a factor on the actuator's whole output, its PD
    torque and its torque limit (a motor weaker or stronger than its datasheet, or a
    battery's sag). Multiplies the Kp/Kd scales above where both are on. (1, 1): off, no
    draw."""
    joint_damping: dict[str, list[float]] = field(default_factory=dict)
    """{joint-name glob: [low, high]}: damping (N m s/rad) of the matching joints."""
    joint_frictionloss_scale: dict[str, list[float]] = field(default_factory=dict)
    """{joint-name glob: [low, high]}: scale of the matching joints' friction loss."""
    action_latency_range: tuple[float, float] = (0.0, 0.0)
    """Seconds from the policy's action to the actuators, per env, drawn at reset as a
    whole number of physics steps (at most one control period), every count between the
    range's ends (rounded to physics steps) equally likely: for that long at the
    start of each control step the actuators keep the previous step's targets, as a
    robot's do while the command is computed and sent. Evaluated with evaluate.py
    --action-latency-ms."""
    observation_delay_range: tuple[float, float] = (0.0, 0.0)
    """Seconds by which the policy's observation lags the simulation, per env, drawn at
    reset as a whole number of physics steps (at most one control period), every count
    between the range's ends (rounded) equally likely: its state terms
    (ang_vel, projected_gravity, joint_pos, joint_vel, and any other term read from the
    trunk and joint state) come from the state that long before the end of the step, as a
    robot's sensors are read, filtered and sent before its policy runs. The history
    records what the policy observed; the critic, rewards and terminations see the
    present. The first observation after a reset has no delay. Evaluated with evaluate.py
    --observation-delay-ms."""
    push_robots: bool = True
    push_interval_s: float = field(default=8.0, metadata={"min": 0.02})
    max_push_vel_xy: float = field(default=0.5, metadata={"min": 0.0})


@dataclass
class RewardsCfg:
    scales: dict[str, float] = field(default_factory=dict)
    """Reward term name -> weight. The term is the env method `_reward_<name>`; weight
    0 switches it off. Weights are multiplied by the policy dt."""
    tracking_sigma: float = field(default=0.25, metadata={"min": 1e-6})
    base_height_target: float = 0.3
    soft_joint_pos_limit: float = field(default=0.9, metadata={"min": 0.0, "max": 1.0})
    soft_joint_vel_limit: float = field(default=0.9, metadata={"min": 0.0, "max": 1.0})
    soft_torque_limit: float = field(default=0.9, metadata={"min": 0.0, "max": 1.0})
    only_positive_rewards: bool = False
    stand_still_max_speed: float | None = field(default=None, metadata={"min": 0.0})
    """stand_still applies only while the trunk's planar speed is below this (m/s), so
    that under a zero command the legs may brake a moving robot or hold it on a slope
    before they are asked to rest; None: whenever the command is zero."""


@dataclass
class TerminationCfg:
    trunk_contact: bool = True
    max_tilt_deg: float | None = None
    """Terminate when the trunk tilts further than this from upright (None: off)."""


@dataclass
class TerrainCfg:
    segments: list[tuple[float, float]] = field(default_factory=list)
    """Planar course along +x (legged_casters/robot/terrain.py): (length m, slope deg) per
    segment, each starting where the previous ended; empty: the flat floor only."""
    start_x: float = 2.0
    """Where the course leaves the floor (robots start at the origin)."""
    width: float = field(default=4.0, metadata={"min": 0.1})
    spawn_on_course: bool = False
    """Reset robots at random places on the course (x in [0, its end + 2 m], |y| up to
    width / 2 - 1 m) instead of the origin: training on its slopes."""
    slope_deg: float = field(default=0.0, metadata={"min": 0.0, "max": 30.0})
    """Largest tilt (deg) of the whole ground, drawn per episode uniformly in [0, slope_deg]
    with a uniformly random downhill direction (so every direction relative to the
    heading). Made by tilting gravity, which for an unbounded plane is the same physics:
    the IMU's projected gravity shows the slope, heights and velocities are along the
    ground. 0: flat. `LeggedEnv.set_ground_slope` fixes it instead (evaluation)."""
    slope_fraction: float = field(default=1.0, metadata={"min": 0.0, "max": 1.0})
    """Share of the episodes drawn on a tilted ground when slope_deg > 0 (the rest flat)."""


@dataclass
class LeggedEnvCfg:
    robot: Literal["caster", "point", "wheel"] = "point"
    num_envs: int | None = field(default=None, metadata={"min": 1})
    """None: 4096 on the Warp backend, the CPU backend's efficient size otherwise."""
    episode_length_s: float = field(default=20.0, metadata={"min": 0.1})
    seed: int = 1
    sim: SimCfg = field(default_factory=SimCfg)
    control: ControlCfg = field(default_factory=ControlCfg)
    commands: CommandsCfg = field(default_factory=CommandsCfg)
    init_state: InitStateCfg = field(default_factory=InitStateCfg)
    noise: NoiseCfg = field(default_factory=NoiseCfg)
    observations: ObservationsCfg = field(default_factory=ObservationsCfg)
    domain_rand: DomainRandCfg = field(default_factory=DomainRandCfg)
    rewards: RewardsCfg = field(default_factory=RewardsCfg)
    termination: TerminationCfg = field(default_factory=TerminationCfg)
    terrain: TerrainCfg = field(default_factory=TerrainCfg)
