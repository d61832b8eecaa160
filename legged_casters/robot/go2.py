"""Unitree Go2 facts: the single source of truth for names, dimensions and limits.

Values are the Go2's published kinematic and inertial data (hip offsets, link
lengths, link masses), joint ranges, motor torque and velocity limits. Everything
else in the package (model builder, envs, export metadata) reads them from here.
"""

from __future__ import annotations

LEGS: tuple[str, ...] = ("FL", "FR", "RL", "RR")
"""Unitree leg order: front-left, front-right, rear-left, rear-right."""

JOINT_KINDS: tuple[str, ...] = ("hip", "thigh", "calf")

ACTUATED_JOINTS: tuple[str, ...] = tuple(f"{leg}_{kind}_joint" for leg in LEGS for kind in JOINT_KINDS)
"""The 12 actuated joints in Unitree order (FL, FR, RL, RR x hip, thigh, calf)."""

SWIVEL_JOINTS: tuple[str, ...] = tuple(f"{leg}_caster_swivel_joint" for leg in LEGS)
WHEEL_JOINTS: tuple[str, ...] = tuple(f"{leg}_caster_wheel_joint" for leg in LEGS)
PASSIVE_JOINTS: tuple[str, ...] = SWIVEL_JOINTS + WHEEL_JOINTS

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
