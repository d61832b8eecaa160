"""Standing up on rolling feet: the bridge's STANDUP targets, from any pose a damped robot
collapses into.

A linear ramp from the measured pose to the default pose fails on casters (docs/deploy.md,
"Starting from the floor"): the feet roll freely, so nothing holds the trunk level while
it rises; the rear legs, which carry more of the weight, lag their targets under the
soft PD gains, the trunk pitches nose-up and the robot ends sitting on its rear casters
and calves, front casters in the air. This stand-up has three phases, all with the
export's gains:

1. **fold** (`fold_time`): the calves fold to the tuck angle, hips and thighs hold where
   they are. Short legs cannot lever the trunk when the thighs move next.
2. **tuck** (`tuck_time`): hips and thighs move to the tuck pose, feet under the hips.
3. **lift** (`lift_time`, the bridge's ``--standup-time``): tuck pose -> default pose
   (``default_joint_pos``), feet staying under the hips.

From the tuck on, two attitude feedbacks act on the targets, read from the trunk's
projected gravity g (the IMU quaternion): each leg extends along the direction that
keeps its foot under its hip (thigh -1/2, calf +1 rad per rad of extension) by
``pitch_gain * g_x * front + roll_gain * g_y * left`` (front/left: +1, rear/right: -1):
legs on the low side push, legs on the high side give way, so the trunk rises level;
and every hip turns by ``-hip_roll_gain * g_y``, which rolls a robot that lies on its
side back onto its feet. Measured with ``scripts/standup_check.py``.

**Righting** (`Righting`, before the fold): a robot that fell lies on its back or its
side, where folding and lifting only push the trunk along the floor. When the trunk is
tilted more than ``RightingCfg.start_tilt_deg`` from upright, the legs first move
through a few keyframes (``RightingCfg.keyframes``), given for the legs on the lower
side and on the upper side of the lying trunk and mirrored left/right by which side is
down (projected gravity's y component at the start), which rolls the trunk onto its
belly; the fold stand-up then starts from the pose the robot is in. The bridge watches
the fold as well: one that tips the trunk past ``abort_tilt_deg`` or ends with it tilted
more than ``stood_tilt_deg`` rights the robot again, up to ``max_tries`` tries in all.
The keyframes were found by a search over simulated falls (``scripts/righting_search.py``).

Driving-wheel joints (velocity control) are not moved: the bridge holds them still.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from legged_casters.robot import go2


@dataclasses.dataclass(frozen=True)
class StandUpCfg:
    fold_time: float = 0.5
    """s: calves fold to the tuck angle, hips and thighs hold."""
    tuck_time: float = 0.7
    """s: hips and thighs move to the tuck pose."""
    lift_time: float = 2.0
    """s: tuck pose -> default pose (the bridge's --standup-time)."""
    tuck: tuple[float, float, float] = (0.0, 1.2, -2.7)
    """Tuck pose (rad) of (hip, thigh, calf): feet under the hips, legs short."""
    pitch_gain: float = 2.0
    """Leg extension (rad) per unit of the projected gravity's x component."""
    roll_gain: float = 2.0
    """Leg extension (rad) per unit of its y component."""
    hip_roll_gain: float = 1.5
    """Hip turn (rad) per unit of its y component."""

    @property
    def duration(self) -> float:
        return self.fold_time + self.tuck_time + self.lift_time


def leg_joints(joint_names: list[str], what: str) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(is a leg joint, kind: 0 hip / 1 thigh / 2 calf / -1 other, front sign, left sign) per
    joint, for names like FL_hip_joint; `what` names the caller in the error raised when the
    12 leg joints of a Go2 are not all there."""
    n = len(joint_names)
    legs, kind, front, left = np.zeros(n, bool), np.full(n, -1), np.zeros(n), np.zeros(n)
    kinds = {"hip": 0, "thigh": 1, "calf": 2}
    for i, name in enumerate(joint_names):
        try:
            leg, k = go2.split_joint_name(name)
        except ValueError:
            continue
        if k not in kinds or leg not in go2.LEGS:
            continue
        legs[i], kind[i] = True, kinds[k]
        front[i], left[i] = go2.leg_signs(leg)
    if legs.sum() != 12:
        raise ValueError(
            f"{what} needs the 12 leg joints of a Go2 (names like FL_hip_joint); the policy has "
            f"{int(legs.sum())} of them in {joint_names}: use the linear stand-up (--standup linear)"
        )
    return legs, kind, front, left


RIGHTING_VALUES = ("hip_out", "thigh_front", "thigh_rear", "calf")
"""What each half of a righting keyframe gives, per leg group: the hip's turn away from the
body (rad; positive moves the foot outwards), the front legs' thigh, the rear legs' thigh
and the calf (rad, the joints' own angles)."""


@dataclasses.dataclass(frozen=True)
class RightingCfg:
    start_tilt_deg: float = 40.0
    """Righting runs first when the trunk is tilted more than this (deg) from upright."""
    stood_tilt_deg: float = 15.0
    """A fold stand-up that ends with the trunk tilted more than this (deg) did not stand
    the robot up (it lay on its side, propped on its legs): righting runs, then the fold
    again (one more try)."""
    abort_tilt_deg: float = 60.0
    """A fold stand-up that tips the trunk past this (deg) stops, and righting starts again
    from where the robot lies (one more try)."""
    keyframes: tuple[tuple[float, ...], ...] = (
        (0.368, 1.059, 4.273, -2.52, 0.988, 3.366, 2.371, -2.591),
        (-0.131, 3.071, 4.459, -1.426, 0.067, 3.265, 3.605, -2.185),
        (-0.974, 2.417, 4.149, -1.653, 0.538, -1.468, 0.566, -1.583),
    )
    """Each keyframe: `RIGHTING_VALUES` for the legs on the lower side, then for the legs on
    the upper side (8 values)."""
    durations: tuple[float, ...] = (0.85, 0.955, 0.995)
    """s: the move to each keyframe (linear in joint space, from the previous one)."""
    settle_time: float = 0.5
    """s: the last keyframe is held this long before the tilt is judged."""
    max_tries: int = 3
    """Stand-up tries (a righting that left the trunk tilted past `start_tilt_deg`, or a
    fold that ended it tilted past `stood_tilt_deg` or tipped it past `abort_tilt_deg`)
    before the stand-up gives up: DAMPING with fault FALLEN."""

    def __post_init__(self):
        if len(self.keyframes) != len(self.durations) or not self.keyframes:
            raise ValueError("righting needs one duration per keyframe, and at least one keyframe")
        if any(len(k) != 2 * len(RIGHTING_VALUES) for k in self.keyframes):
            raise ValueError(f"each righting keyframe has {2 * len(RIGHTING_VALUES)} values")
        if min(self.durations) <= 0 or self.settle_time < 0 or self.max_tries < 1:
            raise ValueError("righting durations must be > 0, settle_time >= 0 and max_tries >= 1")
        if not 0 < self.stood_tilt_deg <= self.start_tilt_deg <= self.abort_tilt_deg <= 180:
            raise ValueError("righting needs 0 < stood_tilt_deg <= start_tilt_deg <= abort_tilt_deg <= 180")

    @property
    def duration(self) -> float:
        return sum(self.durations) + self.settle_time


class Righting:
    """Joint targets that roll a robot with the Go2's legs from its back or side onto its
    belly. Vectorised: `start` may be (..., n) and `side` (...) for a batch of robots."""

    def __init__(self, joint_names: list[str], cfg: RightingCfg, limits=None):
        """`limits` (n, 2): joint position limits (rad) each keyframe is clipped to."""
        self.cfg = cfg
        n = len(joint_names)
        self.legs, kind, front, self.left = leg_joints(joint_names, "righting")
        # which of RIGHTING_VALUES drives each joint: hip 0, thigh 1 (front legs) or 2 (rear), calf 3
        column = np.select([kind == 0, (kind == 1) & (front > 0), kind == 1, kind == 2], [0, 1, 2, 3], 0)
        self.hip = self.legs & (kind == 0)
        k = np.asarray(cfg.keyframes, np.float64).reshape(len(cfg.keyframes), 2, len(RIGHTING_VALUES))
        self.lower = k[:, 0, column]  # (keyframes, n): each joint's target if its leg is on the lower side
        self.upper = k[:, 1, column]  # ... and if it is on the upper side
        lim = np.asarray(limits, np.float64) if limits is not None else np.tile([-np.inf, np.inf], (n, 1))
        if lim.shape != (n, 2):
            raise ValueError(f"righting limits: expected ({n}, 2), got {lim.shape}")
        self.lo, self.hi = lim[:, 0], lim[:, 1]
        self.starts = np.concatenate([[0.0], np.cumsum(cfg.durations)])

    @property
    def duration(self) -> float:
        return self.cfg.duration

    def needed(self, gravity, limit_deg: float | None = None) -> bool:
        """Is the trunk, with projected gravity `gravity` (3,), tilted past `limit_deg`
        (default: the start limit)?"""
        limit = self.cfg.start_tilt_deg if limit_deg is None else limit_deg
        return float(-gravity[2]) < np.cos(np.radians(limit))

    @staticmethod
    def side_down(gravity) -> np.ndarray:
        """+1 where the trunk's left side is the lower one (gravity along +y), else -1."""
        return np.where(np.asarray(gravity)[..., 1] >= 0.0, 1.0, -1.0)

    def pose(self, k: int, side) -> np.ndarray:
        """Keyframe k's joint targets for robots with `side` (...) down."""
        side = np.asarray(side, np.float64)[..., None]
        lower = self.left * side > 0  # the joint's leg is on the lower side
        q = np.where(lower, self.lower[k], self.upper[k])
        q = np.where(self.hip, q * self.left, q)  # hip_out -> the hip's own sign (left legs +, right legs -)
        return np.clip(q, self.lo, self.hi)

    def targets(self, t, start, side) -> np.ndarray:
        """Joint targets at time t (s, scalar or (...)) since righting began from the
        measured pose `start` (..., n) with `side` (...) down (see `side_down`)."""
        start = np.asarray(start, np.float64)
        t = np.asarray(t, np.float64)[..., None]
        q = start
        for k in range(len(self.cfg.keyframes)):
            a = np.clip((t - self.starts[k]) / self.cfg.durations[k], 0.0, 1.0)
            q = q + a * (self.pose(k, side) - q)
        return np.where(self.legs, q, start)


class StandUp:
    """STANDUP joint targets of a robot with the Go2's legs (joint names like FL_hip_joint;
    other joints, e.g. driving wheels, are left as the caller sets them)."""

    def __init__(self, joint_names: list[str], default: np.ndarray, cfg: StandUpCfg = StandUpCfg()):
        self.cfg = cfg
        self.default = np.asarray(default, np.float64).copy()
        self.legs, self.kind, self.front, self.left = leg_joints(joint_names, "the folding stand-up")
        self.tuck = np.where(self.legs, np.asarray(cfg.tuck)[np.clip(self.kind, 0, 2)], self.default)
        self.calf = self.kind == 2
        self.hip = self.kind == 0
        self.extend = np.select([self.kind == 1, self.calf], [-0.5, 1.0], 0.0)
        """Per joint, rad per rad of leg extension that keeps the foot under the hip."""

    @property
    def duration(self) -> float:
        return self.cfg.duration

    def targets(self, t: float, start: np.ndarray, gravity: np.ndarray) -> np.ndarray:
        """Joint targets (rad) at time t (s) since the stand-up began from the measured
        pose `start`, with the trunk's projected gravity `gravity` (3,)."""
        c = self.cfg
        start = np.asarray(start, np.float64)
        folded = np.where(self.calf, self.tuck, start)
        if t < c.fold_time:
            a = t / c.fold_time
            return np.where(self.legs, start + a * (folded - start), start)
        if t < c.fold_time + c.tuck_time:
            a = (t - c.fold_time) / c.tuck_time
            base, lift = folded + a * (self.tuck - folded), 0.0
        else:
            a = min(1.0, (t - c.fold_time - c.tuck_time) / c.lift_time)
            base, lift = self.tuck + a * (self.default - self.tuck), 1.0
        g = np.asarray(gravity, np.float64)
        extension = lift * (c.pitch_gain * g[0] * self.front + c.roll_gain * g[1] * self.left)
        q = base + extension * self.extend - c.hip_roll_gain * g[1] * self.hip
        return np.where(self.legs, q, start)
