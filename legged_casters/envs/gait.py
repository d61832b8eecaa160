"""The skating prior: a command-driven trajectory generator the policy refines.

Section III of the paper says what makes a caster push: a swivel axis tilted
towards the desired motion (alpha > 0 along it) and a caster deflection phi that
keeps changing. This module writes that down as joint-target offsets, computed from
the velocity command, the propulsion-mode mask and a clock phase only, so that the
deployed policy can compute it from what it observes:

* Posture: each leg tilts its caster's swivel axis towards the velocity its foot
  should have, v_i = v_cmd + w_cmd x r_i (r_i: the foot's nominal position in the
  trunk frame). On the Go2's legs the axis pitches with thigh + calf (rad per rad)
  and rolls with minus the hip angle; the thigh/calf split keeps the foot height.
* Oscillation: a sine at `frequency` that deflects the casters across the direction
  of travel: the hips splay the legs sideways (left and right in antiphase) for the
  foot velocity's x part, the thighs swing front and rear legs in antiphase for its
  y part. Casters masked by the propulsion mode do not oscillate.
* Both fade in with the foot's commanded speed (zero command: the nominal pose).
* Speed feedback (`speed_feedback` k > 0, off by default): the planar velocity the
  posture and oscillation aim at becomes `command_share` * v_cmd + k (v_cmd - v_est),
  v_est the actor's own trunk-velocity estimate (legged_casters.learning.estimator).
  Without it the prior pushes equally hard for every command above `full_speed`, so
  the robot accelerates to one speed whatever it is told; with it the push follows
  the speed error, reverses to brake when the robot is too fast, and fades as the
  robot reaches the command.
* Yaw-rate feedback (`yaw_feedback` k_w > 0, off by default): the turning part of each
  foot's push (w x r) uses c_w w_cmd + k_w (w_cmd - w_imu), w_imu the trunk's yaw rate from
  the IMU's gyro (the actor's `ang_vel` observation), so the prior turns harder while the
  robot turns slower than told and less when it turns faster. Unlike the trunk velocity,
  the yaw rate is measured, not estimated.
* A speed law (`amplitude_law`, off by default): the oscillation amplitude for the
  trunk's forward or backward push is read from a measured table of open-loop speed
  against amplitude (scripts/prior_law.py) instead of growing to its full value at
  `full_speed`, so that the prior alone skates at about the commanded speed; the
  sideways and turning part of each foot's push keeps `amplitude` x ramp. A backward
  law alone (`amplitude_law_backward`) changes backward pushes only. A foot takes the
  larger of the law's amplitude and its sideways/turning part's, or with
  `amplitude_law_adds` keeps the prior's own amplitude and gets the law's excess on top.
* Uphill effort (`uphill_gain`, off by default): the oscillation amplitude grows with
  the grade the trunk stands on along the commanded direction, read from the
  projected gravity (an IMU quantity the actor observes), because the push a caster
  makes grows with its deflection (Fig. 3) and a climb needs more push at the same
  speed. Downhill and across-slope it stays as on the flat.

The actor adds this prior to its MLP output (`legged_casters.learning.models.PriorMLPModel`,
in action units); the env applies actions as they come. The export wraps both into
one network, so a robot runs the sum from the observation alone (the clock phase is
an observation term that the deployment bridge computes from its own step counter,
see policy.yaml `gait_clock`). A zero action is therefore the nominal pose, not the
prior: `play.py --policy zero` stands.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import torch

from legged_casters.robot import go2


@dataclass
class GaitPriorCfg:
    enabled: bool = False
    """Put the clock phase in the actor observation and the prior inside the actor."""
    frequency: float = field(default=1.5, metadata={"min": 0.01})
    """Oscillation frequency (Hz); the clock phase advances 2 pi f per second."""
    amplitude: float = field(default=0.15, metadata={"min": 0.0})
    """Oscillation amplitude (rad) at full speed."""
    tilt: float = field(default=0.30, metadata={"min": 0.0})
    """Swivel-axis tilt towards the foot's commanded velocity (rad) at full speed."""
    thigh_share: float = field(default=0.78, metadata={"min": 0.0, "max": 1.0})
    """Share of a pitch tilt made by the thigh (the calf makes the rest); 0.78 keeps the
    foot height to first order in the standing pose."""
    full_speed: float = field(default=0.5, metadata={"min": 1e-3})
    """Foot speed (m/s) at which tilt and amplitude reach their full values (linear ramp)."""
    lateral_gain: float = field(default=1.0, metadata={"min": 0.0})
    """Scale of the lateral (y) tilt relative to the pitch tilt."""
    uphill_gain: float = field(default=0.0, metadata={"min": 0.0})
    """Extra oscillation amplitude (rad) per unit of uphill grade (sine of the slope
    along the commanded direction, from the projected gravity); 0: off. The policy
    observation's training noise on projected_gravity (+-0.05 by default, as large as a
    3 deg grade) passes through this term at this gain: lower it with the term on."""
    uphill_deadband: float = field(default=0.06, metadata={"min": 0.0})
    """Grade (sine) not counted: the trunk of the caster_omni policy pitches 0.044 +- 0.022
    nose-up when it skates on the flat (3 deg of slope add about 0.065)."""
    max_amplitude: float = field(default=0.6, metadata={"min": 0.0})
    """Cap on the oscillation amplitude (rad) with the uphill term."""
    speed_feedback: float = field(default=0.0, metadata={"min": 0.0})
    """Gain k of the speed error in the push velocity (see the module text); 0: the prior
    reads the command alone. Needs a velocity estimate: the actor's estimator."""
    command_share: float = field(default=1.0, metadata={"min": 0.0})
    """Share of the commanded planar velocity in the push velocity (the feedforward);
    only used with speed_feedback > 0."""
    yaw_feedback: float = field(default=0.0, metadata={"min": 0.0})
    """Gain k_w of the yaw-rate error in the turning push (see the module text); 0: the
    prior turns for the command alone. Reads the gyro's yaw rate (the ang_vel observation)."""
    yaw_command_share: float = field(default=1.0, metadata={"min": 0.0})
    """Share of the commanded yaw rate in the turning push (the feedforward); only used with
    yaw_feedback > 0."""
    amplitude_law: list[list[float]] = field(default_factory=list)
    """[[speed m/s, amplitude rad], ...], speeds ascending: the oscillation amplitude for a
    forward push of the trunk at that speed (|vx| of the push velocity), interpolated
    linearly and flat beyond the last point. A foot oscillates with the larger of this and
    `amplitude` x ramp of its push without the trunk's vx (the sideways and turning part).
    Empty (the default): `amplitude` x ramp of the whole push, as before."""
    amplitude_law_backward: list[list[float]] = field(default_factory=list)
    """The same for a backward push (vx < 0); empty: amplitude_law. Given without
    amplitude_law, a forward push keeps the prior's own `amplitude` x ramp (as with no law)."""
    amplitude_law_adds: bool = False
    """How a law meets the rest of a foot's push. False: a foot takes the larger of the law's
    amplitude and `amplitude` x ramp of its push without the trunk's vx. True: it keeps the
    prior's own `amplitude` x ramp of its whole push and the law adds what it gives beyond
    `amplitude` x ramp of the trunk's vx alone, so a law no larger than the ramp changes
    nothing (research/log.md row 111: on the shipped policy the larger-of rule alone, with a law
    equal to the ramp, changed vy +0.4 and added falls)."""
    tilt_backward: float | None = field(default=None, metadata={"min": 0.0})
    """Tilt for a foot whose push points backwards; None: `tilt`."""
    tilt_forward_brake: float | None = field(default=None, metadata={"min": 0.0})
    """Tilt for a foot whose push points forwards while the velocity estimate says the trunk
    rolls backwards (the push brakes a backward roll), blended in from the forward tilt over
    the first `brake_blend_speed` of backward speed; None: off. Needs speed feedback (the
    estimate). The legs brake a backward roll hardest with a nearly flat caster base, a
    forward roll and every drive with a tilted one (research/scripts/brake_limit.py)."""
    brake_blend_speed: float = field(default=0.2, metadata={"min": 1e-3})
    """Backward speed (m/s) of the estimate at which `tilt_forward_brake` takes over fully."""
    stop_pitch: float | None = None
    """The stop pose (None: off): under a zero command (vx, vy and wz all 0) the actor's whole
    action (prior and MLP alike) moves from its last action towards a held pose in which each
    calf is offset by stop_pitch x the leg's end (front +1, rear -1) rad and each hip by
    stop_roll x its side (left +1), a share `stop_rate` of the remaining way per control step.
    The front and rear casters' swivel axes then lean opposite ways, and the pose brakes a
    roll in either direction and holds a slope without oscillating; but a policy trained
    without it falls in a third of its starts out of it (research/log.md, "A stop pose").
    Reads the `actions` observation term (the last action)."""
    stop_roll: float = 0.0
    """Hip offset x side (left +1) of the stop pose, rad. Spreading the hips leans the casters'
    swivel axes outwards and the casters swing round to a new rest, which sets the trunk's
    pitch: with pitch 0.1-0.4 it rests 20-31 deg nose-up, with roll 0.6-0.8 and pitch -0.1 to 0
    within 6 deg of level (research/scripts/pose_hold.py; research/log.md, "What a held pose
    does by itself")."""
    stop_backward_speed: float | None = field(default=None, metadata={"min": 0.0})
    """None (with stop_rest_speed None): the stop pose under every zero command. A speed v
    (m/s): only where the actor's velocity estimate says the trunk rolls backwards faster
    than v when the command is zero, and from then on while it stays zero (the last action
    within half the pose's distance of the pose); a forward roll is left to the actor. The
    legs cannot brake a backward roll by pushing and the pose brakes it in under a second;
    starts out of the pose after a backward roll fell in 0 and 2 of 15 with the two networks
    tried, after a forward one they fall more often (research/log.md, "A stop pose for
    backward rolls only"). Needs the velocity estimator."""
    stop_brakes_commands: bool = False
    """With stop_backward_speed: the pose also where a command that does not ask to go
    backwards (vx >= 0: forwards, sideways, turning) meets a backward roll faster than that
    speed, so that a reversal or a start during a backward roll brakes first and the actor
    takes over near rest; a backward command keeps the actor's own action. False: only zero
    commands. Trained 200 iterations from the flat-stops checkpoint (pitch 0.1, roll 0.3) the
    -2.0 -> +0.5 reversal crossed zero in 1.2 s but fell after it, and starts during and after
    backward stops fell in 16-27 of 56 (research/log.md, "A brake pose with hip roll, and
    starts during and after stops")."""
    stop_rest_speed: float | None = field(default=None, metadata={"min": 0.0})
    """None: off. A speed v (m/s): under a zero command the pose also (with stop_backward_speed)
    or only (without it) where the actor's velocity estimate says the trunk is slower than v,
    |vx| below v, and from then on while the command stays zero: the actor brakes down to v
    and the pose does the rest and holds, on the flat and on a slope. The estimate does not
    see a passive roll, so a small v (nearly still) holds a slope only by that blindness; 0.8
    with a level pose (pitch -0.1, roll 0.7, which brakes a forward roll from 1.0 m/s) stopped
    the flat-stops network from +1.5 and +2.0 in 0.78 / 1.56 s untrained (research/log.md,
    "What a held pose does by itself"). Trained 200 iterations from the flat-stops
    checkpoint (pitch 0.1, roll 0.3, 0.03 m/s) it held the flat and 3 deg (0.07 / 0.13 m)
    but lost the forward stops, and the start after a stand fell: the pose tilts the trunk
    from a stand (research/log.md, "A brake pose with hip roll, and starts during and after
    stops"). Needs the velocity estimator."""
    stop_rate: float = field(default=0.2, metadata={"min": 1e-3, "max": 1.0})
    """Share of the remaining way from the last action to the stop pose covered each control
    step (0.2 at 50 Hz: 95 % in 0.28 s)."""

    def backward_tilt(self) -> float:
        return float(self.tilt if self.tilt_backward is None else self.tilt_backward)

    def forward_brake_tilt(self) -> float:
        return float(self.tilt if self.tilt_forward_brake is None else self.tilt_forward_brake)

    def __post_init__(self):
        if self.tilt_forward_brake is not None and self.speed_feedback <= 0.0:
            raise ValueError("gait.tilt_forward_brake reads the velocity estimate: it needs gait.speed_feedback > 0")
        for name in ("amplitude_law", "amplitude_law_backward"):
            law = getattr(self, name)
            if not law:
                continue
            if any(len(p) != 2 for p in law) or len(law) < 2:
                raise ValueError(f"gait.{name}: give at least two [speed, amplitude] points, got {law}")
            speeds = [p[0] for p in law]
            if any(b <= a for a, b in zip(speeds, speeds[1:], strict=False)) or speeds[0] < 0:
                raise ValueError(f"gait.{name}: speeds must be >= 0 and ascending, got {speeds}")
            if any(p[1] < 0 for p in law):
                raise ValueError(f"gait.{name}: amplitudes must be >= 0, got {law}")

    def law_tensors(self) -> tuple[torch.Tensor, torch.Tensor]:
        """(forward, backward) amplitude laws as (k, 2) tensors; (0, 2) where that direction
        has no law (the backward one falls back to the forward one)."""
        fwd = torch.tensor(self.amplitude_law, dtype=torch.float32).reshape(-1, 2)
        back = torch.tensor(self.amplitude_law_backward or self.amplitude_law, dtype=torch.float32).reshape(-1, 2)
        return fwd, back


FOOT_XY = torch.tensor(
    [
        [go2.leg_signs(leg)[0] * go2.HIP_OFFSET[0], go2.leg_signs(leg)[1] * (go2.HIP_OFFSET[1] + go2.THIGH_OFFSET[1])]
        for leg in go2.LEGS
    ]
)
"""Nominal foot positions in the trunk frame (x, y), m, in go2.LEGS order."""

_SIDE = torch.tensor([go2.leg_signs(leg)[1] for leg in go2.LEGS])  # left +1
_FRONT = torch.tensor([go2.leg_signs(leg)[0] for leg in go2.LEGS])  # front +1


def _law(x: torch.Tensor, law: torch.Tensor) -> torch.Tensor:
    """Piecewise-linear table `law` (k, 2: speed, amplitude; k >= 2) at x, flat beyond its ends."""
    xs, ys = law[:, 0], law[:, 1]
    seg = ((x.unsqueeze(-1) - xs[:-1]) / (xs[1:] - xs[:-1]).clamp(min=1e-9)).clamp(0.0, 1.0)
    return ys[0] + (seg * (ys[1:] - ys[:-1])).sum(-1)


def _prior(
    commands: torch.Tensor,
    mask: torch.Tensor,
    sin_phase: torch.Tensor,
    foot_xy: torch.Tensor,
    side: torch.Tensor,
    front: torch.Tensor,
    tilt: float,
    amplitude: float,
    thigh_share: float,
    full_speed: float,
    lateral_gain: float,
    gravity: torch.Tensor,
    uphill_gain: float,
    uphill_deadband: float,
    max_amplitude: float,
    velocity: torch.Tensor,
    speed_feedback: float,
    command_share: float,
    law_fwd: torch.Tensor,
    law_back: torch.Tensor,
    law_adds: bool,
    tilt_backward: float,
    yaw_rate: torch.Tensor,
    yaw_feedback: float,
    yaw_command_share: float,
    tilt_forward_brake: float,
    brake_blend_speed: float,
) -> torch.Tensor:
    # The planar velocity to push for: the command, or with speed feedback its share plus
    # k times the error of the velocity estimate (n, 2); velocity is unused without it.
    push = commands[:, 0:2]
    if speed_feedback > 0.0:
        push = command_share * push + speed_feedback * (push - velocity[:, 0:2])
    # The yaw rate to turn for: the command, or with yaw feedback its share plus k_w times
    # the gyro's error (n, 1); yaw_rate is unused without it.
    turn = commands[:, 2:3]
    if yaw_feedback > 0.0:
        turn = yaw_command_share * turn + yaw_feedback * (turn - yaw_rate.reshape(-1, 1))
    # Each foot's planar velocity to push for, v + w x r (trunk frame), (n, 4) per axis.
    vx = push[:, 0:1] - turn * foot_xy[:, 1]
    vy = push[:, 1:2] + turn * foot_xy[:, 0]
    speed = torch.sqrt(vx * vx + vy * vy + 1e-12)
    ramp = (speed / full_speed).clamp(max=1.0)
    ux, uy = vx / speed.clamp(min=1e-6), vy / speed.clamp(min=1e-6)
    # the forward tilt (n, 1); with a brake tilt, towards it while the estimate rolls backwards
    tilt_fwd = torch.zeros_like(ux[:, 0:1]) + tilt
    if speed_feedback > 0.0 and tilt_forward_brake != tilt:
        tilt_fwd = tilt_fwd + (tilt_forward_brake - tilt) * (-velocity[:, 0:1] / brake_blend_speed).clamp(0.0, 1.0)
    tilt_x = (tilt_fwd + (tilt_backward - tilt_fwd) * (ux < 0.0).to(ux.dtype)) * ramp * ux
    tilt_y = tilt * lateral_gain * ramp * uy
    amp = torch.zeros_like(sin_phase) + amplitude  # a float, or one per env (scripts/top_speed.py)
    uphill = torch.zeros_like(amp)  # what the uphill term adds to the amplitude
    if uphill_gain > 0.0:
        # the trunk's uphill grade along the commanded planar direction: gravity (trunk
        # frame) pulls backwards against the command when climbing
        cmd_speed = torch.sqrt(commands[:, 0] ** 2 + commands[:, 1] ** 2 + 1e-12)
        along = (gravity[:, 0] * commands[:, 0] + gravity[:, 1] * commands[:, 1]) / cmd_speed.clamp(min=1e-6)
        raised = (amp + uphill_gain * (-along - uphill_deadband).clamp(min=0.0)).clamp(
            max=max(max_amplitude, amplitude)
        )
        uphill = raised - amp
    foot_amp = (amp + uphill).unsqueeze(1) * ramp
    if law_fwd.shape[0] > 0 or law_back.shape[0] > 0:
        # the trunk's forward/backward push from the measured law of its direction, the rest of
        # each foot's push (sideways, turning) as without it; a direction without a law keeps
        # the ramp above; the uphill term adds to both
        px = push[:, 0:1].expand_as(vx)
        vx_amp = amp.unsqueeze(1) * (px.abs() / full_speed).clamp(max=1.0)  # the ramp of the trunk's vx
        rest_amp = amp.unsqueeze(1) * (torch.sqrt((vx - px) ** 2 + vy * vy + 1e-12) / full_speed).clamp(max=1.0)
        for law, along in ((law_fwd, px >= 0.0), (law_back, px < 0.0)):
            if law.shape[0] > 0:
                if law_adds:  # the law's excess over the ramp of the trunk's vx, on top of the prior's own
                    # (foot_amp still holds the prior's own where `along`: the directions are disjoint)
                    law_amp = foot_amp + (_law(px.abs(), law) - vx_amp).clamp(min=0.0)
                else:  # the larger of the law and the ramp of the rest of the push
                    law_amp = torch.maximum(_law(px.abs(), law), rest_amp) + uphill.unsqueeze(1)
                foot_amp = torch.where(along, law_amp, foot_amp)
    wave = sin_phase.unsqueeze(1) * foot_amp * (1.0 - mask)
    hip = -tilt_y + side * wave * ux.abs()
    thigh = thigh_share * tilt_x - front * wave * uy.abs()
    calf = (1.0 - thigh_share) * tilt_x
    return torch.stack([hip, thigh, calf], dim=-1).reshape(-1, 12)


def gait_prior(
    cfg: GaitPriorCfg,
    commands: torch.Tensor,
    mask: torch.Tensor,
    sin_phase: torch.Tensor,
    gravity: torch.Tensor | None = None,
    velocity: torch.Tensor | None = None,
    yaw_rate: torch.Tensor | None = None,
) -> torch.Tensor:
    """Joint-target offsets (n, 12) in rad, go2.ACTUATED_JOINTS order.

    commands (n, 3): vx, vy (m/s), wz (rad/s) in the trunk frame; mask (n, 4): 1 = that
    caster must not oscillate; sin_phase (n,): sine of the clock phase; gravity (n, 3):
    the projected gravity (unit, trunk frame), needed when cfg.uphill_gain > 0;
    velocity (n, >= 2): the trunk's planar velocity (m/s, trunk frame), needed when
    cfg.speed_feedback > 0; yaw_rate (n,): the trunk's yaw rate (rad/s, the gyro's z),
    needed when cfg.yaw_feedback > 0."""
    dev = commands.device
    if yaw_rate is None:
        if cfg.yaw_feedback > 0.0:
            raise ValueError("gait.yaw_feedback needs the trunk's yaw rate")
        yaw_rate = torch.zeros(commands.shape[0], device=dev)
    if velocity is None:
        if cfg.speed_feedback > 0.0:
            raise ValueError("gait.speed_feedback needs the trunk velocity")
        velocity = torch.zeros(commands.shape[0], 2, device=dev)
    if gravity is None:
        if cfg.uphill_gain > 0.0:
            raise ValueError("gait.uphill_gain needs the projected gravity")
        gravity = torch.zeros(commands.shape[0], 3, device=dev)
    law_fwd, law_back = cfg.law_tensors()
    return _prior(
        commands, mask, sin_phase, FOOT_XY.to(dev), _SIDE.to(dev), _FRONT.to(dev),
        cfg.tilt, cfg.amplitude, cfg.thigh_share, cfg.full_speed, cfg.lateral_gain,
        gravity, cfg.uphill_gain, cfg.uphill_deadband, cfg.max_amplitude,
        velocity, cfg.speed_feedback, cfg.command_share,
        law_fwd.to(dev), law_back.to(dev), bool(cfg.amplitude_law_adds), cfg.backward_tilt(),
        yaw_rate, cfg.yaw_feedback, cfg.yaw_command_share, cfg.forward_brake_tilt(), cfg.brake_blend_speed,
    )  # fmt: skip


class GaitPrior(torch.nn.Module):
    """The prior inside the actor: raw policy observation (n, dim) and the actor's
    velocity estimate (n, >= 2; any (n, 0) tensor without speed feedback) -> prior action
    (n, 12) in action units. `slices` gives (start, scale) of the observation terms
    commands, mode_mask and gait_phase, projected_gravity for the uphill term and ang_vel
    for the yaw feedback (the layout is the env's). Scriptable."""

    def __init__(self, cfg: dict, slices: dict[str, list[float]], action_scale: float):
        super().__init__()
        c = GaitPriorCfg(**cfg)
        self.tilt, self.amplitude, self.thigh_share = float(c.tilt), float(c.amplitude), float(c.thigh_share)
        self.full_speed, self.lateral_gain = float(c.full_speed), float(c.lateral_gain)
        self.uphill_gain, self.max_amplitude = float(c.uphill_gain), float(c.max_amplitude)
        self.uphill_deadband = float(c.uphill_deadband)
        self.speed_feedback, self.command_share = float(c.speed_feedback), float(c.command_share)
        self.tilt_backward = c.backward_tilt()
        self.tilt_forward_brake, self.brake_blend_speed = c.forward_brake_tilt(), float(c.brake_blend_speed)
        self.law_adds = bool(c.amplitude_law_adds)
        law_fwd, law_back = c.law_tensors()
        self.register_buffer("law_fwd", law_fwd, persistent=False)
        self.register_buffer("law_back", law_back, persistent=False)
        self.needs_velocity = self.speed_feedback > 0.0
        if self.uphill_gain > 0.0 and "projected_gravity" not in slices:
            raise ValueError("a gait prior with uphill_gain needs the projected_gravity observation slice")
        grav = slices.get("projected_gravity", [0, 1.0])
        self.grav_start, self.grav_scale = int(grav[0]), float(grav[1])
        self.yaw_feedback, self.yaw_command_share = float(c.yaw_feedback), float(c.yaw_command_share)
        if self.yaw_feedback > 0.0 and "ang_vel" not in slices:
            raise ValueError("a gait prior with yaw_feedback needs the ang_vel observation slice")
        gyro = slices.get("ang_vel", [0, 1.0])
        self.yaw_col, self.gyro_scale = int(gyro[0]) + 2, float(gyro[1])  # z of (roll, pitch, yaw) rates
        self.cmd_start, self.cmd_scale = int(slices["commands"][0]), float(slices["commands"][1])
        self.mask_start, self.mask_scale = int(slices["mode_mask"][0]), float(slices["mode_mask"][1])
        self.phase_start, self.phase_scale = int(slices["gait_phase"][0]), float(slices["gait_phase"][1])
        self.action_scale = float(action_scale)
        self.stop_on = c.stop_pitch is not None
        if self.stop_on and "actions" not in slices:
            raise ValueError("a gait prior with stop_pitch needs the actions observation slice (the last action)")
        acts = slices.get("actions", [0, 1.0])
        self.act_start, self.act_scale = int(acts[0]), float(acts[1])
        self.stop_rate = float(c.stop_rate)
        self.stop_backward_on = c.stop_backward_speed is not None
        self.stop_backward_speed = float(c.stop_backward_speed or 0.0)
        self.stop_rest_on = c.stop_rest_speed is not None
        self.stop_rest_speed = float(c.stop_rest_speed or 0.0)
        self.stop_brakes_commands = bool(c.stop_brakes_commands)
        if self.stop_brakes_commands and not self.stop_backward_on:
            raise ValueError("gait.stop_brakes_commands needs gait.stop_backward_speed (the backward roll it brakes)")
        pose = stop_pose(float(c.stop_pitch or 0.0), float(c.stop_roll)) / self.action_scale
        self.register_buffer("stop_action", pose.reshape(1, 12), persistent=False)
        self.register_buffer("foot_xy", FOOT_XY.clone(), persistent=False)
        self.register_buffer("side", _SIDE.clone(), persistent=False)
        self.register_buffer("front", _FRONT.clone(), persistent=False)

    def forward(self, obs: torch.Tensor, velocity: torch.Tensor) -> torch.Tensor:
        commands = obs[:, self.cmd_start : self.cmd_start + 3] / self.cmd_scale
        mask = obs[:, self.mask_start : self.mask_start + 4] / self.mask_scale
        sin_phase = obs[:, self.phase_start] / self.phase_scale
        gravity = obs[:, self.grav_start : self.grav_start + 3] / self.grav_scale
        yaw_rate = obs[:, self.yaw_col] / self.gyro_scale
        offsets = _prior(
            commands, mask, sin_phase, self.foot_xy, self.side, self.front,
            self.tilt, self.amplitude, self.thigh_share, self.full_speed, self.lateral_gain,
            gravity, self.uphill_gain, self.uphill_deadband, self.max_amplitude,
            velocity, self.speed_feedback, self.command_share,
            self.law_fwd, self.law_back, self.law_adds, self.tilt_backward,
            yaw_rate, self.yaw_feedback, self.yaw_command_share, self.tilt_forward_brake, self.brake_blend_speed,
        )  # fmt: skip
        return offsets / self.action_scale

    @torch.jit.export
    def stop(self, obs: torch.Tensor, mean: torch.Tensor, velocity: torch.Tensor) -> torch.Tensor:
        """The actor's mean (n, 12) with the stop pose (GaitPriorCfg.stop_pitch) where the raw
        observation's command is zero (with stop_backward_speed: and the trunk rolls backwards
        by `velocity`, the actor's estimate (n, 3), or the last action is already near the pose;
        with stop_rest_speed likewise where it is slower than that speed either way; with
        stop_brakes_commands also where a command with vx >= 0 meets a backward roll): the last
        action moved `stop_rate` of the way to the pose."""
        if not self.stop_on:
            return mean
        commands = obs[:, self.cmd_start : self.cmd_start + 3]
        last = obs[:, self.act_start : self.act_start + 12] / self.act_scale
        posing = (commands == 0.0).all(dim=1, keepdim=True)
        if self.stop_backward_on or self.stop_rest_on:
            if velocity.shape[1] < 1:
                raise RuntimeError("gait.stop_backward_speed / stop_rest_speed need the actor's velocity estimate")
            near = (last - self.stop_action).pow(2).sum(dim=1, keepdim=True) < 0.25 * self.stop_action.pow(2).sum()
            rolling = velocity[:, 0:1] < -self.stop_backward_speed
            enter = torch.zeros_like(near)
            if self.stop_backward_on:
                enter = enter | rolling
            if self.stop_rest_on:
                enter = enter | (velocity[:, 0:1].abs() < self.stop_rest_speed)
            posing = posing & (near | enter)
            if self.stop_brakes_commands:
                posing = posing | (rolling & (commands[:, 0:1] >= 0.0))
        return torch.where(posing, last + self.stop_rate * (self.stop_action - last), mean)


def stop_pose(pitch: float, roll: float, thigh: float = 0.0) -> torch.Tensor:
    """The stop pose's joint-target offsets (12,), rad, go2.ACTUATED_JOINTS order: each hip roll x
    its side (left +1), each thigh `thigh` and each calf `pitch` x its end (front +1)
    (GaitPriorCfg.stop_pitch)."""
    return torch.stack([roll * _SIDE, thigh * _FRONT, pitch * _FRONT], dim=-1).reshape(12).float()


def advance_phase(phase: torch.Tensor, frequency: float, dt: float) -> torch.Tensor:
    return torch.remainder(phase + 2.0 * math.pi * frequency * dt, 2.0 * math.pi)
