"""Unitree Go2 facts: the single source of truth for names, dimensions and limits.

Values are the Go2's published kinematic and inertial data (hip offsets, link
lengths, link masses), joint ranges, motor torque and velocity limits. Everything
else in the package (model builder, envs, export metadata) reads them from here.
"""

from __future__ import annotations

from dataclasses import dataclass

LEGS: tuple[str, ...] = ("FL", "FR", "RL", "RR")
"""Unitree leg order: front-left, front-right, rear-left, rear-right."""

JOINT_KINDS: tuple[str, ...] = ("hip", "thigh", "calf")

ACTUATED_JOINTS: tuple[str, ...] = tuple(f"{leg}_{kind}_joint" for leg in LEGS for kind in JOINT_KINDS)
"""The 12 actuated joints in Unitree order (FL, FR, RL, RR x hip, thigh, calf)."""

SWIVEL_JOINTS: tuple[str, ...] = tuple(f"{leg}_caster_swivel_joint" for leg in LEGS)
WHEEL_JOINTS: tuple[str, ...] = tuple(f"{leg}_caster_wheel_joint" for leg in LEGS)
PASSIVE_JOINTS: tuple[str, ...] = SWIVEL_JOINTS + WHEEL_JOINTS

DRIVE_WHEEL_JOINTS: tuple[str, ...] = tuple(f"{leg}_wheel_joint" for leg in LEGS)
"""The driving-wheel robot's 4 actuated wheel joints (FL, FR, RL, RR)."""

UNITREE_LEG_ORDER: tuple[str, ...] = ("FR", "FL", "RR", "RL")
"""The order of the legs in Unitree's low-level messages (LowState/LowCmd motor_state,
motor_cmd): motor index = 3 * position of the leg here + (hip 0, thigh 1, calf 2).
Our order (LEGS) swaps left and right. Source: the LegID table of Unitree's SDK and
its Go2 stand example (docs/protocol.md); not checked on a robot."""

UNITREE_MOTOR: dict[str, int] = {
    **{
        f"{leg}_{kind}_joint": 3 * UNITREE_LEG_ORDER.index(leg) + k
        for leg in LEGS
        for k, kind in enumerate(JOINT_KINDS)
    },
    **{f"{leg}_wheel_joint": 12 + UNITREE_LEG_ORDER.index(leg) for leg in LEGS},
}
"""Joint name -> motor index in Unitree's LowState/LowCmd. The Go2-W's wheel motors are
12-15 in the same leg order (third-party Go2-W configurations; not checked on a robot)."""

TRUNK_BODY = "trunk"
IMU_SITE = "imu"
ROOT_JOINT = "root"

# --- geometry (m) -------------------------------------------------------------
HIP_OFFSET = (0.1934, 0.0465, 0.0)  # hip joint from trunk origin; signs per leg
THIGH_OFFSET = (0.0, 0.0955, 0.0)  # thigh joint from hip joint; y sign per side
THIGH_LENGTH = 0.213
CALF_LENGTH = 0.213
TRUNK_SIZE = (0.3762, 0.0935, 0.114)  # full box extents used for collision/inertia
FOOT_RADIUS = 0.022  # point-foot sphere (Go2 rubber foot)

# --- masses (kg) ----------------------------------------------------------------
TRUNK_MASS = 6.921
HIP_MASS = 0.678
THIGH_MASS = 1.152
CALF_MASS = 0.241  # includes the foot of the point-foot robot
GO2_PUBLISHED_MASS_RANGE = (14.5, 15.5)  # the published Go2 weighs about 15 kg

# --- joint limits ---------------------------------------------------------------
HIP_RANGE = (-1.0472, 1.0472)
FRONT_THIGH_RANGE = (-1.5708, 3.4907)
REAR_THIGH_RANGE = (-0.5236, 4.5379)
CALF_RANGE = (-2.7227, -0.83776)
TORQUE_LIMIT = {"hip": 23.7, "thigh": 23.7, "calf": 45.43}  # N m
VELOCITY_LIMIT = {"hip": 30.1, "thigh": 30.1, "calf": 20.07}  # rad/s

# Reflected rotor inertia of the Go2 joint motors (kg m^2), a common modelling value.
MOTOR_ARMATURE = 0.01

# --- driving wheels (robot "wheel") -----------------------------------------------------
# We found no published wheel specification of Unitree's wheeled Go2 (Go2-W); these are
# stated choices of the size of its tyres, see docs/robot.md.
DRIVE_WHEEL_RADIUS = 0.09  # m
DRIVE_WHEEL_WIDTH = 0.04  # m
DRIVE_WHEEL_MASS = 0.6  # kg each: tyre, rim and hub motor
DRIVE_WHEEL_OFFSET = 0.035  # m, wheel mid-plane outboard of the calf axis
# The wheel motors: the Go2's hip motor limits, assumed to be the same motor family.
DRIVE_WHEEL_TORQUE_LIMIT = 23.7  # N m
DRIVE_WHEEL_VELOCITY_LIMIT = 30.1  # rad/s (2.7 m/s at the rim)
# Velocity servo tau = KD_WHEEL (dq_target - dq), like a LowCmd with kp 0. At 2 N m s/rad
# the wheel follows a target within ~0.02 s under the robot's load.
DRIVE_WHEEL_KD = 2.0

# --- PD gains of the position actuators -------------------------------------------
# The caster robot needs stiff legs to stand: with Kp 40 the loaded legs splay, the
# casters deflect and the robot creeps (4-12 cm in 20 s); Kp 60 / Kd 1.5 holds it
# within ~3 cm for swivel damping anywhere in the randomised range [0.01, 0.1].
# Measured with tests/test_robot_physics.py::test_stands_still.
KP = {"hip": 60.0, "thigh": 60.0, "calf": 60.0}
KD = {"hip": 1.5, "thigh": 1.5, "calf": 1.5}

# --- nominal standing pose (rad), also the policy's default joint positions --------
NOMINAL_POSE = {"hip": 0.0, "thigh": 0.8, "calf": -1.5}


def joint_range(leg: str, kind: str) -> tuple[float, float]:
    if kind == "hip":
        return HIP_RANGE
    if kind == "thigh":
        return FRONT_THIGH_RANGE if leg.startswith("F") else REAR_THIGH_RANGE
    if kind == "calf":
        return CALF_RANGE
    raise ValueError(f"unknown joint kind {kind!r}; expected one of {JOINT_KINDS}")


def split_joint_name(name: str) -> tuple[str, str]:
    """'FL_thigh_joint' -> ('FL', 'thigh')."""
    leg, kind, _ = name.split("_")
    return leg, kind


def leg_signs(leg: str) -> tuple[float, float]:
    """(x sign, y sign) of a leg: front +x, left +y."""
    return (1.0 if leg[0] == "F" else -1.0, 1.0 if leg[1] == "L" else -1.0)


def mirror_joint(name: str) -> tuple[str, float]:
    """The joint that mirrors `name` across the trunk's sagittal (x-z) plane and the sign
    that maps its angle: 'FL_hip_joint' -> ('FR_hip_joint', -1.0). Left and right swap;
    a hinge about the trunk's x or z axis (the hips, the caster swivels) turns the other
    way in the mirror image, one about the y axis (thighs, calves, wheels) the same way."""
    leg, rest = name[:2], name[2:]
    if leg not in LEGS:
        raise ValueError(f"{name!r} is not a Go2 leg joint (it must start with one of {LEGS})")
    kind = rest.split("_")[1]
    flips = kind == "hip" or rest.startswith("_caster_swivel")
    return leg[0] + ("R" if leg[1] == "L" else "L") + rest, (-1.0 if flips else 1.0)


def mirror_legs() -> list[int]:
    """LEGS order -> the index of each leg's mirror image (FL <-> FR, RL <-> RR)."""
    return [LEGS.index(leg[0] + ("R" if leg[1] == "L" else "L")) for leg in LEGS]


def default_joint_positions() -> list[float]:
    return [NOMINAL_POSE[split_joint_name(j)[1]] for j in ACTUATED_JOINTS]


def torque_limits() -> list[float]:
    return [TORQUE_LIMIT[split_joint_name(j)[1]] for j in ACTUATED_JOINTS]


def velocity_limits() -> list[float]:
    return [VELOCITY_LIMIT[split_joint_name(j)[1]] for j in ACTUATED_JOINTS]


def joint_ranges() -> list[tuple[float, float]]:
    return [joint_range(*split_joint_name(j)) for j in ACTUATED_JOINTS]


def kp() -> list[float]:
    return [KP[split_joint_name(j)[1]] for j in ACTUATED_JOINTS]


def kd() -> list[float]:
    return [KD[split_joint_name(j)[1]] for j in ACTUATED_JOINTS]


CONTROL_POSITION = "position"
CONTROL_VELOCITY = "velocity"


@dataclass(frozen=True)
class ActionLayout:
    """What each action component drives, in action order: the one source every consumer
    (model builder, env, export metadata, bridge, simulated robot) reads.

    A position joint's target is default + action_scale * action (rad) with PD gains
    kp/kd; a velocity joint's target is velocity_scale * action (rad/s), tracked with kd
    alone (kp 0). `default` is 0 for velocity joints."""

    joints: tuple[str, ...]
    control: tuple[str, ...]
    default: tuple[float, ...]
    kp: tuple[float, ...]
    kd: tuple[float, ...]
    torque_limits: tuple[float, ...]
    velocity_limits: tuple[float, ...]
    ranges: tuple[tuple[float, float], ...]
    """Position limits of position joints; +-velocity limit of velocity joints."""

    def __len__(self) -> int:
        return len(self.joints)

    @property
    def position_mask(self) -> tuple[bool, ...]:
        return tuple(c == CONTROL_POSITION for c in self.control)

    @property
    def num_legs_joints(self) -> int:
        return sum(self.position_mask)


FOOT_KINDS = ("caster", "point", "wheel")
"""The Go2's feet: passive casters, point feet (the trotting baseline), driving wheels."""


def action_layout(feet: str) -> ActionLayout:
    """The action layout of the Go2 with `feet` 'caster', 'point' (12 leg joints) or
    'wheel' (12 leg joints, then 4 wheel joints)."""
    legs = dict(
        joints=ACTUATED_JOINTS,
        control=(CONTROL_POSITION,) * 12,
        default=tuple(default_joint_positions()),
        kp=tuple(kp()),
        kd=tuple(kd()),
        torque_limits=tuple(torque_limits()),
        velocity_limits=tuple(velocity_limits()),
        ranges=tuple(joint_ranges()),
    )
    if feet in ("caster", "point"):
        return ActionLayout(**legs)
    if feet == "wheel":
        n = len(DRIVE_WHEEL_JOINTS)
        v = DRIVE_WHEEL_VELOCITY_LIMIT
        return ActionLayout(
            joints=ACTUATED_JOINTS + DRIVE_WHEEL_JOINTS,
            control=legs["control"] + (CONTROL_VELOCITY,) * n,
            default=legs["default"] + (0.0,) * n,
            kp=legs["kp"] + (0.0,) * n,
            kd=legs["kd"] + (DRIVE_WHEEL_KD,) * n,
            torque_limits=legs["torque_limits"] + (DRIVE_WHEEL_TORQUE_LIMIT,) * n,
            velocity_limits=legs["velocity_limits"] + (v,) * n,
            ranges=legs["ranges"] + ((-v, v),) * n,
        )
    raise ValueError(f"unknown feet {feet!r}; expected 'caster', 'point' or 'wheel'")
