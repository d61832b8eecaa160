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


class StandUp:
    """STANDUP joint targets of a robot with the Go2's legs (joint names like FL_hip_joint;
    other joints, e.g. driving wheels, are left as the caller sets them)."""

    def __init__(self, joint_names: list[str], default: np.ndarray, cfg: StandUpCfg = StandUpCfg()):
        self.cfg = cfg
        n = len(joint_names)
        self.default = np.asarray(default, np.float64).copy()
        self.legs = np.zeros(n, bool)
        self.kind = np.full(n, -1)
        front, left = np.zeros(n), np.zeros(n)
        kinds = {"hip": 0, "thigh": 1, "calf": 2}
        for i, name in enumerate(joint_names):
            try:
                leg, kind = go2.split_joint_name(name)
            except ValueError:
                continue
            if kind not in kinds or leg not in go2.LEGS:
                continue
            self.legs[i], self.kind[i] = True, kinds[kind]
            front[i], left[i] = go2.leg_signs(leg)
        if self.legs.sum() != 12:
            raise ValueError(
                f"the folding stand-up needs the 12 leg joints of a Go2 (names like FL_hip_joint); the policy has "
                f"{int(self.legs.sum())} of them in {joint_names}: use the linear stand-up (--standup linear)"
            )
        self.front, self.left = front, left
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
