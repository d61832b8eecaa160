"""evaluate: a policy through fixed scenarios, noise and randomisation off.

    python scripts/evaluate.py                         # newest caster_omni run, else the shipped policy
    python scripts/evaluate.py --load_run <run> --checkpoint 500
    python scripts/evaluate.py --policy resources/policies/caster_omni   # an exported folder / policy.pt

Every scenario runs in its own env of one batched env, from a standing start, with
the command schedule it names; errors are trunk-frame velocity errors averaged over
the scenario's measurement window (after the robot has had time to reach speed).
The same code, with the `quick` scenario set, is the deterministic evaluation that
train.py runs every few iterations (TensorBoard `Eval/...`).
"""

from __future__ import annotations

import argparse
import bisect
import concurrent.futures
import contextlib
import math
import multiprocessing
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
import yaml
from tensordict import TensorDict

from legged_casters.tools import common
from legged_casters.tools.common import UsageError
from legged_casters.utils.math import wrap_to_pi, yaw_from_quat

PROG = "evaluate.py"


@dataclass(frozen=True)
class Scenario:
    name: str
    segments: tuple[tuple[float, tuple[float, float, float]], ...]
    """(start time s, command (vx, vy, wz)) pieces; the last holds to the end."""
    duration: float = 8.0
    measure_from: float = 3.0
    """Errors are averaged from this time to the end."""
    mode: str = "four_wheel"
    copies: int = 1
    random_commands: bool = False
    """Commands drawn from the task's ranges every 5 s instead of `segments`; pushes on."""
    kind: str = "track"
    push_interval: float = 8.0
    """Seconds between pushes of a random-commands scenario (PUSH_VEL each)."""
    start_x: float | None = None
    """Start at this x on the evaluation hill (HILL_SEGMENTS) instead of the origin."""
    slope_deg: float = 0.0
    """The whole ground tilted by this much (LeggedEnv.set_ground_slope) ..."""
    downhill_yaw: float = 0.0
    """... falling towards this world yaw (rad): 0 is straight ahead of the starting robot
    (it faces +x), pi straight behind it."""

    def command(self, t: float) -> tuple[float, float, float]:
        cmd = self.segments[0][1]
        for start, c in self.segments:
            if t >= start:
                cmd = c
        return cmd


def _const(name: str, cmd, **kw) -> Scenario:
    return Scenario(name, ((0.0, cmd),), **kw)


TRACKING = (
    _const("vx +0.5", (0.5, 0.0, 0.0)),
    _const("vx -0.5", (-0.5, 0.0, 0.0)),
    _const("vx +1.0", (1.0, 0.0, 0.0)),
    _const("vx -1.0", (-1.0, 0.0, 0.0)),
    _const("vx +2.0", (2.0, 0.0, 0.0)),
    _const("vy +0.4", (0.0, 0.4, 0.0)),
    _const("vy -0.4", (0.0, -0.4, 0.0)),
    _const("wz +0.8", (0.0, 0.0, 0.8)),
    _const("wz -0.8", (0.0, 0.0, -0.8)),
)
BRAKE_AT_S = 6.0
"""s: the brake scenarios command their first speed this long before the stop or reversal."""


def _brake(name: str, before: float, after: float) -> Scenario:
    return Scenario(name, ((0.0, (before, 0.0, 0.0)), (BRAKE_AT_S, (after, 0.0, 0.0))), BRAKE_AT_S + 6.0,
                    BRAKE_AT_S + 2.0, kind="brake")  # fmt: skip


def _slope(name: str, cmd: float, deg: float, downhill_ahead: bool, duration: float = 10.0) -> Scenario:
    kind = "hold" if cmd == 0.0 else "slope"
    return _const(name, (cmd, 0.0, 0.0), duration=duration, measure_from=0.0 if kind == "hold" else 4.0, kind=kind,
                  slope_deg=deg, downhill_yaw=0.0 if downhill_ahead else math.pi)  # fmt: skip


GO_STOPPED_S = 2.0
"""s: the go-again scenarios hold the zero command this long before the new one (the stop bar)."""
GO_EARLY_S = 0.6
"""s: the go-during-a-stop scenarios give the new command this long after the zero command,
while the robot still rolls (a joystick let go and pushed again)."""
GO_WINDOW_S = (3.0, 6.0)
"""s after the new command: the window over which a go-again scenario's error is measured."""


def _short(value: float) -> str:
    """+0.5, +0.25, +2.0: two decimals where the second one says something."""
    text = f"{value:+.2f}"
    return text[:-1] if text.endswith("0") else text


def _axis(cmd: tuple[float, float, float]) -> str:
    """The first axis ("vx", "vy" or "wz") a command moves along."""
    return next(k for k, c in zip(("vx", "vy", "wz"), cmd, strict=True) if c)


def _go_again(before: float, after: tuple[float, float, float], stopped: float = GO_STOPPED_S) -> Scenario:
    """Move at vx `before` for 4 s (stand 1 s when 0), a zero command for `stopped` s, then
    `after`: a start out of whatever a stop left (pose, casters, speed); with GO_EARLY_S, a
    start during the stop."""
    move = 4.0 if before else 1.0
    start = move + (stopped if before else 0.0)
    axis = _axis(after)
    origin = f"a stop from {_short(before)}" if before else "a stand"
    when = f"{stopped:g} s into" if before and stopped < GO_STOPPED_S else "after"
    stop = ((move, (0.0, 0.0, 0.0)),) if before else ()
    return Scenario(f"go {when} {origin}: {axis} {_short(sum(after))}",
                    ((0.0, (before, 0.0, 0.0)), *stop, (start, after)),
                    start + GO_WINDOW_S[1], start + GO_WINDOW_S[0], kind="go")  # fmt: skip


STOP = (
    _brake("stop from +1.5", 1.5, 0.0),
    _brake("stop from -1.5", -1.5, 0.0),
    _brake("stop from +2.0", 2.0, 0.0),
    _brake("stop from -2.0", -2.0, 0.0),
    _brake("reverse +2.0 to -0.5", 2.0, -0.5),
    _brake("reverse -2.0 to +0.5", -2.0, 0.5),
    _const("hold flat", (0.0, 0.0, 0.0), duration=10.0, measure_from=0.0, kind="hold"),
    _slope("hold 3deg", 0.0, 3.0, True, duration=6.0),
    _slope("vx +0.5 down 3deg", 0.5, 3.0, True),
    _slope("vx +0.5 up 3deg", 0.5, 3.0, False),
    _slope("vx -0.5 down 3deg", -0.5, 3.0, False),
    _slope("vx -0.5 up 3deg", -0.5, 3.0, True),
    _slope("hold 5deg", 0.0, 5.0, True, duration=6.0),
    _slope("vx +0.5 down 5deg", 0.5, 5.0, True),
    _slope("vx +0.5 up 5deg", 0.5, 5.0, False),
    _go_again(0.0, (0.5, 0.0, 0.0)),
    *(_go_again(1.0, after) for after in ((1.0, 0.0, 0.0), (-0.5, 0.0, 0.0), (0.0, 0.4, 0.0), (0.0, 0.0, 0.8))),
    *(_go_again(-1.0, after) for after in ((0.5, 0.0, 0.0), (-1.0, 0.0, 0.0), (0.0, 0.4, 0.0), (0.0, 0.0, 0.8))),
    *(_go_again(-1.5, after, GO_EARLY_S) for after in ((0.5, 0.0, 0.0), (0.0, 0.4, 0.0), (0.0, 0.0, 0.8))),
    *(_go_again(1.5, after, GO_EARLY_S) for after in ((0.0, 0.4, 0.0), (0.0, 0.0, 0.8))),
)
"""Stopping, starting again and slopes: a zero command at speed (rest = |vx| below REST_SPEED
from then to the end), reversals at speed (time until vx crosses zero), zero commands held on
the flat and on 3 and 5 deg of ground tilted ahead of or behind the robot, +-0.5 m/s down and
up those slopes (a command with the sign of the downhill direction goes down), and starts
after a stand, after a stop and during one (error over GO_WINDOW_S after the new command)."""
REST_SPEED = 0.1
"""m/s: a stopped robot's |vx| stays below this."""
STOP_BARS = {"rest_s": 2.0, "rest_m": 1.5, "cross_s": 2.0}
"""Stopping bars: at rest within 2.0 s and 1.5 m of the zero command; a reversal's vx crosses
zero within 2.0 s of the new command."""
HOLD_BARS = {"hold flat": (0.1, 5.0), "hold 3deg": (0.3, None)}
"""Zero-command bars: hold scenario -> (largest distance from the start m, largest heading
change deg or None) over the whole scenario (10 s flat, 6 s on the slope)."""
SLOPE_VX_ERROR = 0.2
"""m/s: the mean |vx error| bar of the 3 deg slope scenarios (5 deg: no fall)."""

FULL = TRACKING + (
    Scenario(
        "fig6 step", ((0.0, (0.0, 0.0, 0.0)), (2.0, (-0.6, 0.0, 0.0)), (6.0, (0.6, 0.0, 0.0))), 10.0, 6.0, kind="step"
    ),  # fmt: skip
    _const("mode four_wheel", (0.8, 0.0, 0.0), mode="four_wheel", kind="mode"),
    _const("mode front_wheel", (0.8, 0.0, 0.0), mode="front_wheel", kind="mode"),
    _const("mode rear_wheel", (0.8, 0.0, 0.0), mode="rear_wheel", kind="mode"),
    Scenario("random+pushes", ((0.0, (0.0, 0.0, 0.0)),), 100.0, 0.0, copies=4, random_commands=True, kind="random"),
)
FULL = FULL + STOP
QUICK = tuple(
    Scenario(s.name, s.segments, 5.0, 2.0)
    for s in TRACKING
    if s.name in ("vx +0.5", "vx -0.5", "vx +1.0", "vy +0.4", "vy -0.4", "wz +0.8", "wz -0.8")
) + (
    # 8 robots under random commands (redrawn once, at 5 s), pushed every 1.5 s: only its
    # falls count (the training's model_best must not be a checkpoint that tracks well and
    # falls when pushed). 5 s, one command each, caught none of the falls that 10 s catches
    # (docs/tasks.md): they come after the command changes.
    Scenario("pushes", ((0.0, (0.0, 0.0, 0.0)),), 10.0, 0.0, copies=8, random_commands=True, kind="random",
             push_interval=1.5),
)  # fmt: skip
TOP_SPEED = {"forward": 2.5, "backward": 3.5}
"""m/s, the open-loop top speeds of the caster model, rounded down (scripts/top_speed.py, docs/tasks.md)."""
SLALOM_PERIOD_S = 2.25
"""The vy slalom: vx 0.8 m/s, vy +0.4 / -0.4 m/s alternating every this many seconds."""
RAMP_TARGET, RAMP_S = -4.0, 6.0
"""The Fig. 9 ramp: vx from 0 to RAMP_TARGET m/s over RAMP_S seconds, then held."""
HILL_DEG = 3.0
HILL_START_X = 100.0
HILL_SEGMENTS = ((30.0, HILL_DEG), (2.0, 0.0), (30.0, -HILL_DEG))
"""The evaluation hill (terrain.segments from HILL_START_X along +x): 30 m up at 3 deg, 2 m
flat, 30 m down; far enough from the origin that no flat-ground scenario reaches it."""
DOWNHILL_X = HILL_START_X + 30.0 * math.cos(math.radians(HILL_DEG)) + 2.0 + 1.0
"""The downhill hold starts 1 m into the descent, facing down it (+x)."""


def _speed(name: str, cmd, long: bool) -> Scenario:
    return _const(name, cmd, duration=10.0 if long else 8.0, measure_from=5.0 if long else 3.0)


SPEED = tuple(
    _speed(f"vx {sign * v:+.2f}", (sign * v, 0.0, 0.0), v >= 1.5)
    for v in (0.25, 0.5, 1.0, 1.5, 2.0)
    for sign in (1, -1)
) + (
    _speed(f"vx top {TOP_SPEED['forward']:+.1f}", (TOP_SPEED["forward"], 0.0, 0.0), True),
    _speed(f"vx top {-TOP_SPEED['backward']:+.1f}", (-TOP_SPEED["backward"], 0.0, 0.0), True),
) + tuple(
    _speed(f"vy {sign * v:+.2f}", (0.0, sign * v, 0.0), False) for v in (0.2, 0.4, 0.6) for sign in (1, -1)
) + (
    Scenario(
        "vy slalom",
        tuple((2.0 + k * SLALOM_PERIOD_S, (0.8, 0.4 if k % 2 == 0 else -0.4, 0.0)) for k in range(8)),
        2.0 + 8 * SLALOM_PERIOD_S, 2.0, kind="slalom",
    ),
    Scenario(
        "fig9 ramp",
        tuple((k * 0.25, (RAMP_TARGET * min(k * 0.25 / RAMP_S, 1.0), 0.0, 0.0)) for k in range(int(RAMP_S / 0.25) + 1)),
        RAMP_S + 4.0, 0.0, kind="ramp",
    ),
    _const("downhill 3deg", (0.5, 0.0, 0.0), duration=10.0, measure_from=4.0, kind="hill", start_x=DOWNHILL_X),
)  # fmt: skip
"""The speed sweep: vx from 0.25 m/s to the top speed both ways, vy, the vy
slalom, the Fig. 9 backward ramp (the slalom starts with 2 s of vx 0.8 alone) and the
downhill hold (vx 0.5 down the evaluation hill's 3 deg descent, from a stand on it)."""
SPEED_BARS = {"vx": ((1.5, 0.15), (2.0, 0.3)), "vy": ((0.4, 0.1),)}
"""The speed sweep's bars: axis -> ((up to this |command|, max mean |error|), ...)."""
SLALOM_SWING, SLALOM_HEADING_DEG = (0.3, 0.6), 30.0
RAMP_BEST_2S = 2.0
DOWNHILL_VX_ERROR = 0.2
ESTIMATOR_RMS = 0.1

SCENARIO_SETS = {"full": FULL, "quick": QUICK, "speed": SPEED, "stop": STOP, "all": FULL + SPEED}

THRESHOLDS = {
    "vx +0.5": ("vx", 0.15), "vx -0.5": ("vx", 0.15), "vx +1.0": ("vx", 0.15), "vx -1.0": ("vx", 0.15),
    "vx +2.0": ("vx", 0.3), "vy +0.4": ("vy", 0.15), "vy -0.4": ("vy", 0.15),
    "wz +0.8": ("wz", 0.25), "wz -0.8": ("wz", 0.25),
}  # fmt: skip
"""The tracking bars: scenario -> (axis, max mean |error|)."""
TASK_BARS = {"go2_wheel_flat": {"vx": 0.1, "wz": 0.2}}
"""Per-task bars per axis that replace THRESHOLDS' (the driving-wheel baseline's)."""
STEP_SIGN_CHANGE_S = 1.5
SIGN_CHANGE_MARGIN = 0.05
"""m/s: after the Fig. 6 step, the sign has changed once vx exceeds this (not mere jitter)."""
MODE_SWIVEL_RATIO = 0.2
MODE_VX_ERROR = 0.25
CMD_PROBE = 0.5
"""m/s added to the vx command to measure `est_cmd_gain`."""
PUSH_VEL = 0.5
"""m/s: each push adds U(-PUSH_VEL, PUSH_VEL) to the trunk's vx and vy."""
FALL_CAUSE_S = 1.0
"""s: a fall in a random-command scenario counts as `falls_after_push` (`falls_after_cmd`)
when it comes at most this long after the robot's last push (its last new command)."""


EVAL_SETTINGS = {
    "noise.enabled": False,
    "noise.bias": {},
    "domain_rand.push_robots": False,
    "domain_rand.randomize_friction": False,
    "domain_rand.randomize_base_mass": False,
    "domain_rand.randomize_com": False,
    "domain_rand.randomize_gains": False,
    "domain_rand.motor_strength_range": (1.0, 1.0),
    "domain_rand.joint_damping": {},
    "domain_rand.joint_frictionloss_scale": {},
    "domain_rand.action_latency_range": (0.0, 0.0),
    "domain_rand.observation_delay_range": (0.0, 0.0),
    "init_state.joint_pos_noise": 0.0,
    "init_state.base_vel_noise": 0.0,
    "init_state.random_yaw": False,
    "commands.curriculum": False,
    "terrain.segments": [],
    "terrain.spawn_on_course": False,
    "terrain.slope_deg": 0.0,
}
"""What makes an env an evaluation env: no noise, no randomisation, a standing start at
the origin on flat ground (a task trained on a terrain course is evaluated on the flat floor; the
slope experiments add their course explicitly, scripts/reproduce.py)."""


def applicable(scenarios, env_class, env_cfg) -> tuple[Scenario, ...]:
    """The scenarios a task can be asked to do: none that commands more than the task is
    ever commanded in training (its command ranges, vx up to the curriculum's limit;
    e.g. no vy for the wheel robot, whose range is [0, 0]), no propulsion-mode scenario
    for a task without modes."""
    limits = env_cfg.commands.limits()
    keep = []
    for s in scenarios:
        if s.kind == "mode" and not hasattr(env_class, "set_mode"):
            continue
        if any(not lo <= c[a] <= hi for _, c in s.segments for a, (lo, hi) in enumerate(limits)):
            continue
        keep.append(s)
    return tuple(keep)


def eval_env_cfg(env_cfg, scenarios, backend: str = "cpu", condition: dict | None = None, terrain_of=None):
    """The evaluation env's config; `condition`: more overrides (a row of SIM2SIM);
    `terrain_of`: the scenario set whose ground to build (default `scenarios`), so that a
    subset runs on the same ground as the whole set."""
    n = sum(s.copies for s in scenarios)
    longest = max(s.duration for s in scenarios)
    fields = {**EVAL_SETTINGS, "num_envs": n, "episode_length_s": longest + 1.0, "sim.backend": backend}
    fields["sim.device"] = "cpu" if backend == "cpu" else env_cfg.sim.device
    if any(s.start_x is not None for s in (terrain_of or scenarios)):
        fields.update({"terrain.segments": [list(seg) for seg in HILL_SEGMENTS], "terrain.start_x": HILL_START_X})
    fields.update(condition or {})
    return common.with_overrides(env_cfg, fields, "evaluation env")


IMU_BIAS = {"ang_vel": 0.05, "projected_gravity": 0.035}
"""The IMU bias of evaluate.py --imu-bias (noise.bias): up to +-0.05 rad/s on each gyro axis
and +-0.035 on each projected-gravity component (a mount tilted up to 2 deg), drawn per
scenario robot."""


def condition_overrides(
    env_cfg,
    physics_dt: float | None = None,
    latency_ms: float = 0.0,
    noise: bool = False,
    imu_bias: bool = False,
    obs_delay_ms: float = 0.0,
):
    """Env overrides that evaluate a policy off its training conditions, same control period:
    another physics step (the decimation follows), a fixed action latency, the training's
    observation noise, an IMU bias (IMU_BIAS), a fixed observation delay."""
    out: dict = {}
    control_dt = env_cfg.sim.timestep * env_cfg.sim.decimation if env_cfg.sim.timestep else None
    if physics_dt is not None:
        if control_dt is None:
            raise UsageError(
                "another physics step (--physics-dt, --sim2sim, --robot-clock) needs a task whose config sets "
                "sim.timestep (give it with --set sim.timestep=... when training)"
            )
        decimation = round(control_dt / physics_dt)
        if decimation < 1 or abs(decimation * physics_dt - control_dt) > 1e-9:
            raise UsageError(
                f"--physics-dt {physics_dt:g}: the control period {control_dt:g} s must be a whole number of physics "
                "steps"
            )
        out.update({"sim.timestep": physics_dt, "sim.decimation": decimation})
    for flag, key, ms in (
        ("--action-latency-ms", "domain_rand.action_latency_range", latency_ms),
        ("--observation-delay-ms", "domain_rand.observation_delay_range", obs_delay_ms),
    ):
        if ms:
            if ms < 0 or (control_dt is not None and ms / 1e3 > control_dt + 1e-9):
                raise UsageError(f"{flag} {ms:g}: must be between 0 and the control period")
            out[key] = (ms / 1e3, ms / 1e3)
    if noise:
        out["noise.enabled"] = True
    if imu_bias:
        out["noise.bias"] = dict(IMU_BIAS)
    return out


SIM2SIM = (
    ("5 ms physics (training)", {}),
    ("2 ms physics", {"physics_dt": 0.002}),
    ("10 ms action latency", {"latency_ms": 10.0}),
    ("20 ms action latency", {"latency_ms": 20.0}),
    ("20 ms observation delay", {"obs_delay_ms": 20.0}),
    ("observation noise on", {"noise": True}),
    ("IMU bias", {"imu_bias": True}),
    ("2 ms + 20 ms latency + noise", {"physics_dt": 0.002, "latency_ms": 20.0, "noise": True}),
)
"""The rows of evaluate.py --sim2sim: the training conditions first, then one change each."""

ROBOT_CLOCK = ("5 ms physics (training)", "2 ms physics", "20 ms action latency")
"""The rows of SIM2SIM that the robot-clock check names (--robot-clock): the training conditions and
the two it judges against them."""

SIM2SIM_TOLERANCE = {"lin": 0.05, "ang": 0.1}
"""The robot-clock check's sim-to-sim bar: under another condition every check that measures an error
stays within 0.05 m/s (vx, vy, the estimator's RMS) or 0.1 rad/s (wz) of its value in the
first condition, and the robots fall no more often (over the same seeds)."""


Policy = Callable[[TensorDict], torch.Tensor]


@dataclass
class ScenarioResult:
    name: str
    kind: str
    cmd: tuple[float, float, float]
    mean: dict[str, float] = field(default_factory=dict)
    """Mean trunk-frame vx, vy, wz over the window."""
    err: dict[str, float] = field(default_factory=dict)
    """Mean |error| of vx, vy, wz over the window."""
    falls: int = 0
    extra: dict[str, float] = field(default_factory=dict)
    slope_deg: float = 0.0


def _schedule(scenarios, owner: list[int], steps: int, dt: float, ranges: dict, gen: torch.Generator):
    """Each env's command at every step (steps, n, 3), and whether its scenario is still
    running (steps, n). Random scenarios redraw from the task's ranges every 5 s."""
    n = len(owner)
    cmds = torch.zeros(steps, n, 3)
    times = torch.arange(steps) * dt
    block = int(round(5.0 / dt))
    for j, i in enumerate(owner):
        s = scenarios[i]
        if s.random_commands:
            for k0 in range(0, steps, block):
                for c, key in enumerate(("lin_vel_x", "lin_vel_y", "ang_vel_yaw")):
                    lo, hi = ranges[key]
                    cmds[k0 : k0 + block, j, c] = lo + (hi - lo) * torch.rand(1, generator=gen).item()
        else:
            for start, c in s.segments:
                cmds[times >= start, j] = torch.tensor(c, dtype=torch.float32)
    alive = times.unsqueeze(1) <= torch.tensor([scenarios[i].duration for i in owner]).unsqueeze(0)
    return cmds, alive


def falls_after(fall_steps: list[int], event_steps: list[int], window_steps: int) -> int:
    """How many of one robot's falls (step indices) come at most `window_steps` after one of
    its events (pushes or new commands, step indices, ascending) at or before the fall."""
    count = 0
    for f in fall_steps:
        k = bisect.bisect_right(event_steps, f)  # events at or before the fall: event_steps[:k]
        count += k > 0 and f - event_steps[k - 1] <= window_steps
    return count


def run_scenarios(
    env, policy: Policy, scenarios=QUICK, seed: int = 0, estimator=None, command_gain: bool = False
) -> list[ScenarioResult]:
    """Run `policy` (TensorDict obs -> actions) on `env` (an evaluation env with one env
    per scenario copy) through `scenarios`; return one result per scenario. `estimator`
    (TensorDict obs -> (n, 3) trunk velocity estimate, m/s): its RMS error per scenario
    (extra `est_rms`) and the mean vx it estimates (`est_vx`, beside the measured mean vx:
    a robot that stands under a small command while its estimate reads the command shows
    it), and with `command_gain` how far its vx moves per m/s of commanded
    vx in its input (extra `est_cmd_gain`: the estimate again with the vx command
    CMD_PROBE m/s higher; 0 for an estimator that does not read the command)."""
    dev = env.device
    n = env.num_envs
    owner = [i for i, s in enumerate(scenarios) for _ in range(s.copies)]
    if len(owner) != n:
        raise ValueError(f"the evaluation env has {n} envs, the scenarios need {len(owner)}")
    owner_t = torch.tensor(owner, device=dev)
    gen = torch.Generator().manual_seed(seed)
    if hasattr(env, "set_mode"):
        for i, s in enumerate(scenarios):
            env.set_mode(s.mode, (owner_t == i).nonzero().flatten())
    env.set_commands(torch.zeros(n, 3))
    if any(s.start_x is not None for s in scenarios):
        if env.course is None:
            raise ValueError("a scenario starts on the evaluation hill: build the env by eval_env_cfg(cfg, scenarios)")
        env.spawn_x = torch.tensor([math.nan if scenarios[i].start_x is None else scenarios[i].start_x for i in owner])
    if hasattr(env, "set_ground_slope"):  # every run sets every env's ground (flat where none is named)
        env.set_ground_slope(torch.tensor([scenarios[i].slope_deg for i in owner], device=dev),
                             torch.tensor([scenarios[i].downhill_yaw for i in owner], device=dev))  # fmt: skip
    obs = env.reset()
    steps = int(round(max(s.duration for s in scenarios) / env.dt))
    cmds_all, alive = _schedule(scenarios, owner, steps, env.dt, env.command_ranges, gen)
    random_ids = torch.tensor([j for j, i in enumerate(owner) if scenarios[i].random_commands], dtype=torch.long)
    push_every = torch.tensor([max(1, int(round(scenarios[owner[j]].push_interval / env.dt))) for j in random_ids])
    vel_log = torch.zeros(steps, n, 3)
    power_log = torch.zeros(steps, n)  # positive mechanical power of all actuated joints (W)
    pos_log = torch.zeros(steps, n, 2)
    swivel_log = torch.zeros(steps, n, 4) if hasattr(env, "swivel_vel") else None
    yaw_log = torch.zeros(steps, n)
    est_log = torch.zeros(steps, n) if estimator is not None else None  # squared estimate error
    est_vx_log = torch.zeros(steps, n) if estimator is not None else None  # the estimate's vx
    gain_log = torch.zeros(steps, n) if estimator is not None and command_gain else None
    if gain_log is not None:
        cmd_col, cmd_scale = env.policy_obs_slices()["commands"]  # the vx command's column and scale
    fall_log = torch.zeros(steps, n, dtype=torch.bool)  # counted falls (fall attribution: FALL_CAUSE_S)
    push_log = torch.zeros(steps, n, dtype=torch.bool)
    for k in range(steps):
        cmd = cmds_all[k]
        changed = not torch.equal(env.commands.cpu(), cmd)
        env.commands[:] = cmd.to(dev)
        if changed:  # the policy sees a new command at once, not one step late (history as in training)
            obs = env.refresh_commands(obs)
        pushed = random_ids[k % push_every == 0] if k and len(random_ids) else random_ids[:0]
        if len(pushed):
            ids = pushed.to(dev)
            qvel = env.sim.qvel[ids].clone()
            qvel[:, 0:2] += (torch.rand(len(ids), 2, generator=gen).to(dev) * 2 - 1) * PUSH_VEL
            env.sim.reset(ids, env.sim.qpos[ids].clone(), qvel)
            push_log[k, pushed] = True
        with torch.no_grad():
            actions = policy(obs)
            if est_log is not None:  # the estimate the actor used for this step's action
                est = estimator(obs).cpu()
                est_log[k] = (est - env.base_lin_vel.cpu()).pow(2).sum(dim=1)
                est_vx_log[k] = est[:, 0]
            if gain_log is not None:
                shifted = obs.clone()
                shifted["policy"][:, cmd_col] += CMD_PROBE * cmd_scale
                gain_log[k] = (estimator(shifted).cpu()[:, 0] - est[:, 0]) / CMD_PROBE
        obs = env.step(actions)[0]
        fall_log[k] = (env.terminated_buf & ~env.time_out_buf).cpu() & alive[k]
        vel_log[k] = torch.cat([env.base_lin_vel[:, :2], env.base_ang_vel[:, 2:3]], dim=1).cpu()
        power_log[k] = env.positive_power().cpu()
        pos_log[k] = env.base_pos[:, :2].cpu()
        yaw_log[k] = yaw_from_quat(env.base_quat).cpu()
        if swivel_log is not None:
            swivel_log[k] = env.swivel_vel.cpu()
    falls = fall_log.sum(dim=0)
    cmd_log = torch.zeros(steps, n, dtype=torch.bool)  # a new command at step k (from the schedule)
    cmd_log[1:] = (cmds_all[1:] != cmds_all[:-1]).any(dim=2)

    def steps_of(log: torch.Tensor, j: int) -> list[int]:
        return log[:, j].nonzero().flatten().tolist()

    results = []
    for i, s in enumerate(scenarios):
        cols = [j for j, o in enumerate(owner) if o == i]
        k0, k1 = int(round(s.measure_from / env.dt)), int(round(s.duration / env.dt))
        v = vel_log[k0:k1, cols]
        c = cmds_all[k0:k1, cols]
        r = ScenarioResult(s.name, s.kind, s.command(s.duration), slope_deg=s.slope_deg)
        for a, key in enumerate(("vx", "vy", "wz")):
            r.mean[key] = float(v[..., a].mean())
            r.err[key] = float((v[..., a] - c[..., a]).abs().mean())
        r.falls = int(falls[cols].sum())
        if s.random_commands:
            window = int(round(FALL_CAUSE_S / env.dt))
            for name, log in (("falls_after_push", push_log), ("falls_after_cmd", cmd_log)):
                r.extra[name] = sum(falls_after(steps_of(fall_log, j), steps_of(log, j), window) for j in cols)
        cmd = s.command(s.duration)
        if s.kind == "track" and cmd[0] != 0.0 and cmd[1] == 0.0 and cmd[2] == 0.0:
            r.extra["cot"] = cost_of_transport(env, power_log[k0:k1, cols[0]], pos_log[k0:k1, cols[0]])
            r.extra["power_w"] = float(power_log[k0:k1, cols[0]].mean())
        if s.kind == "step":
            t_step = s.segments[-1][0]
            ks = int(round(t_step / env.dt))
            # vel_log[k] is the velocity after step k, i.e. at time (k + 1) dt.
            vx = vel_log[ks:k1, cols[0], 0]
            before = float(vel_log[ks - int(round(1.0 / env.dt)) : ks, cols[0], 0].mean())
            positive = (vx > SIGN_CHANGE_MARGIN).nonzero().flatten()
            reversed_ = before < -SIGN_CHANGE_MARGIN and len(positive) > 0
            # No backward motion before the step, no sign change to time: that fails the check.
            r.extra["sign_change_s"] = float(positive[0] + 1) * env.dt if reversed_ else math.inf
            r.extra["vx_before_step"] = before
        if s.kind == "brake":
            r.extra.update(_brake_measures(s, vel_log[:, cols[0], 0], pos_log[:, cols[0]], k1, env.dt))
        if s.kind == "hold":
            start = pos_log[0, cols[0]]
            r.extra["max_drift_m"] = float(torch.linalg.norm(pos_log[:k1, cols[0]] - start, dim=1).max())
            turn = wrap_to_pi(yaw_log[:k1, cols[0]] - yaw_log[0, cols[0]])
            r.extra["max_turn_deg"] = math.degrees(float(turn.abs().max()))
        if est_log is not None:
            r.extra["est_rms"] = float(est_log[k0:k1, cols].mean().sqrt())
            r.extra["est_vx"] = float(est_vx_log[k0:k1, cols].mean())
        if gain_log is not None:
            r.extra["est_cmd_gain"] = float(gain_log[k0:k1, cols].mean())
        if s.kind == "slalom":
            y = pos_log[k0:k1, cols[0], 1]
            heading = wrap_to_pi(yaw_log[k0:k1, cols[0]] - yaw_log[k0, cols[0]])
            r.extra["swing_m"] = float(y.max() - y.min()) / 2.0
            r.extra["heading_deg"] = math.degrees(float(heading.abs().max()))
        if s.kind == "ramp":
            window = int(round(2.0 / env.dt))
            vx = vel_log[:k1, cols[0], 0]
            alive_steps = int(alive[:k1, cols[0]].sum())
            means = vx.unfold(0, window, 1).mean(dim=1) if len(vx) >= window else vx.mean().reshape(1)
            r.extra["best_2s_backward"] = float(-means.min()) if alive_steps else 0.0
        if s.kind == "mode" and swivel_log is not None:
            rms = swivel_log[k0:k1, cols[0]].pow(2).mean(0).sqrt()
            mask = torch.tensor(env.cfg.modes.masks[s.mode], dtype=torch.bool)
            for leg, value in zip(("FL", "FR", "RL", "RR"), rms.tolist(), strict=True):
                r.extra[f"swivel_rms_{leg}"] = value
            if mask.any():
                r.extra["masked_over_driven"] = float(rms[mask].mean() / rms[~mask].mean().clamp(min=1e-9))
        results.append(r)
    return results


def _brake_measures(s: Scenario, vx: torch.Tensor, xy: torch.Tensor, k1: int, dt: float) -> dict[str, float]:
    """A brake scenario's measurements (vx (steps,), xy (steps, 2): after each step, i.e.
    index k is time (k + 1) dt): the speed when the new command came (`v_at_cmd`); for a
    stop the time and path from it until |vx| stays below REST_SPEED to the end
    (`rest_s`, `rest_m`; inf when it never does); for a reversal the time until vx first
    has the new command's sign (`cross_s`, inf when it never does)."""
    t_cmd, target = s.segments[-1][0], s.segments[-1][1][0]
    kc = int(round(t_cmd / dt))  # vx[kc - 1]: the velocity at the new command's time
    out = {"v_at_cmd": float(vx[kc - 1])}
    after = vx[kc:k1]
    if target == 0.0:
        moving = (after.abs() >= REST_SPEED).nonzero().flatten()
        last = int(moving[-1]) + 1 if len(moving) else 0  # steps after the command until rest for good
        if last >= len(after):
            out["rest_s"], out["rest_m"] = math.inf, math.inf
        else:
            path = xy[kc - 1 : kc + last]
            out["rest_s"] = last * dt
            out["rest_m"] = float(torch.linalg.norm(path[1:] - path[:-1], dim=1).sum()) if last else 0.0
    else:
        crossed = (after * math.copysign(1.0, target) > 0.0).nonzero().flatten()
        out["cross_s"] = float(crossed[0] + 1) * dt if len(crossed) else math.inf
    return out


def cost_of_transport(env, power: torch.Tensor, xy: torch.Tensor) -> float:
    """The paper's mechanical cost of transport: positive work of all actuated joints
    (wheels included) over weight x distance travelled. `power` (steps,) W is each
    policy step's mean over its physics substeps (env.positive_power: every physics
    step on the MuJoCo C backend), `xy` (steps, 2) m the trunk's path."""
    mass = float(env.model.body_subtreemass[env.trunk_id])
    distance = float(torch.linalg.norm(xy[1:] - xy[:-1], dim=1).sum())
    work = float(power.sum()) * env.dt
    return work / (mass * 9.81 * distance) if distance > 1e-6 else math.inf


def summary(results: list[ScenarioResult]) -> dict[str, float]:
    """Scalars for TensorBoard: mean |error| per axis over the tracking scenarios, falls, and
    each tracking scenario's error on its own axis as `scenario/<name>` (e.g. `scenario/wz_+0.8`
    beside `scenario/wz_-0.8`: a policy that turns one way only shows there)."""
    track = [r for r in results if r.kind == "track"]
    out = {}
    for key in ("vx", "vy", "wz"):
        rel = [r.err[key] for r in track if r.name.startswith(key)]
        if rel:
            out[f"{key}_error"] = float(np.mean(rel))
    for r in track:
        axis = r.name.split()[0]
        if axis in r.err:
            out["scenario/" + r.name.replace(" ", "_")] = float(r.err[axis])
    out["falls"] = float(sum(r.falls for r in results))
    est = [r.extra["est_rms"] for r in track if "est_rms" in r.extra]
    if est:
        out["estimator_rms"] = float(np.mean(est))
    return out


def verdict(results: list[ScenarioResult], task: str | None = None) -> list[tuple[str, bool, str]]:
    """(check, passed, measured) against the tracking bars (TASK_BARS for a task with its own)."""
    checks = []
    by = {r.name: r for r in results}
    bars = TASK_BARS.get(task or "", {})
    for name, (axis, bar) in THRESHOLDS.items():
        bar = bars.get(axis, bar)
        if name in by:
            e = by[name].err[axis]
            checks.append((f"{name}: |{axis} error| <= {bar}", e <= bar, f"{e:.3f}"))
    if "fig6 step" in by:
        t = by["fig6 step"].extra["sign_change_s"]
        checks.append(
            (f"fig6 step: vx changes sign within {STEP_SIGN_CHANGE_S} s", t <= STEP_SIGN_CHANGE_S, f"{t:.2f} s")
        )
    if "random+pushes" in by:
        f = by["random+pushes"].falls
        checks.append(("random commands + pushes: 0 falls", f == 0, str(f)))
    for r in results:  # the speed sweep (scenario names "vx +0.25", "vy -0.4", ...; not the 15 checks)
        if r.kind != "track" or r.name in THRESHOLDS or r.name.startswith("vx top"):
            continue
        axis = r.name[:2]
        value = abs(r.cmd[0 if axis == "vx" else 1])
        bar = next((b for limit, b in SPEED_BARS.get(axis, ()) if value <= limit + 1e-9), None)
        if bar is not None:
            checks.append((f"{r.name}: |{axis} error| <= {bar}", r.err[axis] <= bar, f"{r.err[axis]:.3f}"))
    if "vy slalom" in by:
        r = by["vy slalom"]
        lo, hi = SLALOM_SWING
        swing, heading = r.extra["swing_m"], r.extra["heading_deg"]
        checks.append((f"vy slalom: lateral swing {lo}-{hi} m", lo <= swing <= hi and not r.falls,
                       _with_falls(f"{swing:.2f} m", r.falls)))  # fmt: skip
        checks.append((f"vy slalom: heading change < {SLALOM_HEADING_DEG} deg", heading < SLALOM_HEADING_DEG,
                       f"{heading:.0f} deg"))  # fmt: skip
    if "fig9 ramp" in by:
        best = by["fig9 ramp"].extra["best_2s_backward"]
        checks.append((f"fig9 ramp: best 2-s backward speed >= {RAMP_BEST_2S} m/s", best >= RAMP_BEST_2S,
                       f"{best:.2f} m/s"))  # fmt: skip
    if "downhill 3deg" in by:
        r = by["downhill 3deg"]
        ok = r.err["vx"] <= DOWNHILL_VX_ERROR and not r.falls
        measured = _with_falls(f"{r.err['vx']:.3f}", r.falls)
        checks.append((f"downhill 3deg: |vx error| <= {DOWNHILL_VX_ERROR}", ok, measured))
    for r in results:
        if r.kind == "brake" and "rest_s" in r.extra:
            t, d = r.extra["rest_s"], r.extra["rest_m"]
            ok = t <= STOP_BARS["rest_s"] and d <= STOP_BARS["rest_m"] and not r.falls
            checks.append((f"{r.name}: at rest within {STOP_BARS['rest_s']} s and {STOP_BARS['rest_m']} m", ok,
                           _with_falls(f"{t:.2f} s, {d:.2f} m", r.falls)))  # fmt: skip
        elif r.kind == "brake":
            t = r.extra["cross_s"]
            ok = t <= STOP_BARS["cross_s"] and not r.falls
            checks.append((f"{r.name}: vx crosses zero within {STOP_BARS['cross_s']} s", ok,
                           _with_falls(f"{t:.2f} s", r.falls)))  # fmt: skip
        elif r.kind == "hold" and r.name in HOLD_BARS:
            dist, turn = HOLD_BARS[r.name]
            d, y = r.extra["max_drift_m"], r.extra["max_turn_deg"]
            ok = d < dist and (turn is None or y < turn) and not r.falls
            bar = f"< {dist} m" + (f" and < {turn:g} deg" if turn is not None else "")
            measured = _with_falls(f"{d:.2f} m, {y:.0f} deg", r.falls)
            checks.append((f"{r.name}: zero command moves it {bar}", ok, measured))
        elif r.kind == "slope" and r.slope_deg <= 3.0:
            ok = r.err["vx"] <= SLOPE_VX_ERROR and not r.falls
            checks.append((f"{r.name}: |vx error| <= {SLOPE_VX_ERROR}", ok, _with_falls(f"{r.err['vx']:.3f}", r.falls)))
        elif r.kind == "go":
            axis = _axis(r.cmd)
            bar = bars.get(axis, min(b for a, b in THRESHOLDS.values() if a == axis))
            ok = r.err[axis] <= bar and not r.falls
            measured = _with_falls(f"{r.err[axis]:.3f}", r.falls)
            checks.append((f"{r.name}: |{axis} error| <= {bar}, no fall", ok, measured))
    steep = [r for r in results if r.kind in ("hold", "slope") and r.slope_deg > 3.0]
    if steep:
        n = sum(r.falls for r in steep)
        deg = max(r.slope_deg for r in steep)
        checks.append((f"{deg:g} deg slope: 0 falls (hold, up, down)", n == 0, str(n)))
    est = [r.extra["est_rms"] for r in results if r.kind == "track" and "est_rms" in r.extra]
    if est:
        worst = max(est)
        checks.append((f"estimator RMS error <= {ESTIMATOR_RMS} m/s (worst flat scenario)", worst <= ESTIMATOR_RMS,
                       f"{worst:.3f}"))  # fmt: skip
    for mode in ("front_wheel", "rear_wheel"):
        r = by.get(f"mode {mode}")
        if r is None:
            continue
        ratio = r.extra.get("masked_over_driven", math.nan)
        checks.append(
            (f"{mode}: masked/driven swivel RMS <= {MODE_SWIVEL_RATIO}", ratio <= MODE_SWIVEL_RATIO, f"{ratio:.2f}")
        )
        checks.append((f"{mode}: |vx error| <= {MODE_VX_ERROR}", r.err["vx"] <= MODE_VX_ERROR, f"{r.err['vx']:.3f}"))
    return checks


def _with_falls(measured: str, falls: int) -> str:
    """A check's measurement, with its falls after it where the check also fails for them."""
    return measured + (f" ({falls} fall{'s' if falls > 1 else ''})" if falls else "")


def format_table(results: list[ScenarioResult]) -> str:
    lines = [
        "| scenario | command (vx, vy, wz) | mean vx | mean vy | mean wz "
        "| abs err vx | abs err vy | abs err wz | falls | notes |",
        "|---|---|---:|---:|---:|---:|---:|---:|---:|---|",
    ]
    for r in results:
        cmd = "random" if r.kind == "random" else "({}, {}, {})".format(*(_short(c) for c in r.cmd))
        notes = ", ".join(f"{k} {v:.2f}" for k, v in r.extra.items())
        lines.append(
            f"| {r.name} | {cmd} | {r.mean['vx']:+.2f} | {r.mean['vy']:+.2f} | {r.mean['wz']:+.2f} | "
            f"{r.err['vx']:.3f} | {r.err['vy']:.3f} | {r.err['wz']:.3f} | {r.falls} | {notes} |"
        )
    return "\n".join(lines)


@contextlib.contextmanager
def _rng_kept():
    """Run a block without changing torch's and numpy's global random state."""
    np_state = np.random.get_state()
    with torch.random.fork_rng(devices=[]):
        yield
    np.random.set_state(np_state)


def actor_estimator(actor):
    """The training actor's velocity estimate (TensorDict obs -> (n, 3)), or None without an estimator."""
    return actor.estimate if getattr(actor, "estimator", None) is not None else None


def exported_estimator(module):
    """An exported TorchScript policy's `estimate` (obs -> (n, 3)), or None where it has none."""
    if not hasattr(module, "estimate"):
        return None
    probe = module.estimate(torch.zeros(1, int(module.obs_dim)))
    return (lambda obs: module.estimate(obs["policy"])) if probe.shape[-1] == 3 else None


class DeterministicEval:
    """The periodic evaluation inside train.py: a small env built once, the quick scenarios."""

    def __init__(self, spec, env_cfg, scenarios=QUICK):
        self.scenarios = applicable(scenarios, spec.env_class, env_cfg)
        with _rng_kept():  # building and running it leave training's random streams alone
            self.env = spec.env_class(eval_env_cfg(env_cfg, self.scenarios))

    def __call__(self, actor) -> dict[str, float]:
        was_training = actor.training
        actor.eval()
        with _rng_kept():
            return self._run(actor, was_training)

    def _run(self, actor, was_training: bool) -> dict[str, float]:
        try:
            device = next(actor.parameters()).device
            est = actor_estimator(actor)
            results = run_scenarios(
                self.env, lambda obs: actor(obs.to(device)), self.scenarios,
                estimator=(lambda obs: est(obs.to(device))) if est is not None else None,
            )  # fmt: skip
        finally:
            actor.train(was_training)
        return summary(results)

    def close(self) -> None:
        self.env.close()


def symmetrised(policy, env):
    """policy made exactly left-right symmetric: the mean of its action for the observation
    and the mirror image of its action for the mirrored observation (the maps of
    legged_casters.learning.symmetry). A diagnostic: it tells a policy's one-sidedness from
    what its symmetric part does."""
    from legged_casters.learning.symmetry import mirror_action, mirror_observation

    if env.mirror_maps().get("policy") is None:
        raise UsageError(f"--symmetrise: {type(env).__name__}'s policy observation has no mirror image")
    return lambda obs: 0.5 * (policy(obs) + mirror_action(env, policy(mirror_observation(env, obs))))


# --- CLI ------------------------------------------------------------------------------------
def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog=PROG, description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    common.add_run_selection_flags(p)
    p.add_argument("--policy", help="an exported policy folder or its policy.pt (instead of a run)")
    p.add_argument("--scenarios", choices=sorted(SCENARIO_SETS), default="full")
    p.add_argument("--stochastic", action="store_true", help="checkpoints only: sample actions with the actor's noise")
    p.add_argument("--physics-dt", type=float, help="physics step (s), same control period (default: the task's)")
    p.add_argument("--action-latency-ms", type=float, default=0.0, help="action latency (ms, whole physics steps)")
    p.add_argument(
        "--observation-delay-ms", type=float, default=0.0, help="observation delay (ms, whole physics steps)"
    )
    p.add_argument("--noise", action="store_true", help="with the training's observation noise")
    p.add_argument("--imu-bias", action="store_true", help="with a constant IMU bias per robot (IMU_BIAS)")
    p.add_argument(
        "--seed",
        type=int,
        default=0,
        help="seed of the random commands and pushes of the random-command scenarios (default 0: the numbers the "
        "docs quote); another seed redraws them, to see how much a fall count owes to the draw",
    )
    p.add_argument(
        "--seeds",
        metavar="LIST",
        help="after the run at the first seed, the random-command scenarios again under each further seed (the "
        "tracking scenarios do not depend on the seed): their falls per seed and in total; '0-4' or '0,3,7'. With "
        "--sim2sim under every condition, and the table of SIM2SIM_TOLERANCE (the robot-clock bar)",
    )
    p.add_argument(
        "--symmetrise",
        action="store_true",
        help="run the policy made exactly left-right symmetric (the mean of its action and the mirror image of its "
        "action for the mirrored observation): a diagnostic, docs/tasks.md",
    )
    p.add_argument(
        "--checkpoints",
        metavar="LIST",
        help="rank several checkpoints of the run through the scenarios: a comma list of iterations and 'best' "
        "(500,750,best), or 'all' (every model_<it>.pt and model_best.pt); ordered by falls, then checks passed",
    )
    p.add_argument(
        "--jobs",
        type=int,
        default=1,
        help="with --checkpoints: evaluate this many checkpoints at once, each in its own process (one per core "
        "is a good choice; default 1)",
    )
    p.add_argument(
        "--select",
        action="store_true",
        help="with --checkpoints: record the first of the ranking in the run's selected.yaml, the checkpoint play, "
        "evaluate and export then load when no --checkpoint is given",
    )
    p.add_argument(
        "--sim2sim",
        action="store_true",
        help="the checks under each condition of SIM2SIM (5 ms, 2 ms, latency, observation delay, noise, IMU bias) "
        "and their change from 5 ms",
    )
    p.add_argument(
        "--robot-clock",
        action="store_true",
        help="only the conditions of the robot-clock check (5 ms, 2 ms physics, 20 ms action latency) and its "
        "tolerance table; with --checkpoints each checkpoint under all three, ranked: fewest falls at 5 ms, then "
        "within the bar, then fewest falls in all, then most checks passed (--seeds counts the falls over several "
        "draws)",
    )
    return p


def load_exported(path: Path, task_arg: str | None):
    """An exported policy.pt (or its folder) -> (task, spec, env cfg, policy, label, obs dim)."""
    file = path / "policy.pt" if path.is_dir() else path
    if not file.is_file() or file.suffix != ".pt":
        raise UsageError(f"--policy {path}: expected an exported folder with policy.pt, or a policy.pt file")
    exp = common.read_export(file, task_arg)
    try:
        module = torch.jit.load(str(file), map_location="cpu").eval()
    except RuntimeError as err:
        raise common.CheckpointError(
            f"{file} cannot be loaded as an exported TorchScript policy: the file is damaged or was not written by "
            "export.py",
            str(err),
        ) from None
    policy = lambda obs: module(obs["policy"])  # noqa: E731
    policy.estimate = exported_estimator(module)
    return exp.task, exp.spec, exp.env_cfg, policy, f"{file}", exp.obs_dim


def checkpoint_policy(actor, stochastic: bool) -> Policy:
    """A training actor as a policy (TensorDict obs -> actions: its mean, or sampled with its
    noise), carrying the actor's velocity estimate as `.estimate` (None without one)."""
    policy = lambda obs: actor(obs, stochastic_output=stochastic)  # noqa: E731
    policy.estimate = actor_estimator(actor)
    return policy


def single_condition(args: argparse.Namespace, env_cfg) -> tuple[str, dict]:
    """(name, overrides) of the one condition --physics-dt/--action-latency-ms/--observation-delay-ms/--noise/
    --imu-bias give."""
    cond = condition_overrides(
        env_cfg, args.physics_dt, args.action_latency_ms, args.noise, args.imu_bias, args.observation_delay_ms
    )
    return (", ".join(f"{k}={v}" for k, v in cond.items()) or "training conditions") + _seed_note(args), cond


def parse_seeds(text: str) -> list[int]:
    """--seeds: '0-4' -> [0, 1, 2, 3, 4]; '0,3,7' -> [0, 3, 7]; ranges and commas mix."""
    seeds: list[int] = []
    try:
        for part in text.split(","):
            lo, sep, hi = part.strip().partition("-")
            first, last = int(lo), int(hi) if sep else int(lo)
            if first < 0 or last < first:
                raise ValueError
            seeds += [k for k in range(first, last + 1) if k not in seeds]
    except ValueError:
        raise UsageError(f"--seeds {text!r}: expected seeds >= 0 as a list or ranges, e.g. 0-4 or 0,3,7") from None
    return seeds


def _seed_note(args: argparse.Namespace) -> str:
    """', seed N' for a condition's name when --seed is not the default 0."""
    return f", seed {args.seed}" if args.seed else ""


def run_policy(env, policy: Policy, scenarios, symmetrise: bool, seed: int = 0) -> list[ScenarioResult]:
    """run_scenarios for the CLI: the policy (made symmetric with --symmetrise), its estimate
    (`policy.estimate`, if it has one) and the estimate's command gain; `seed`: --seed."""
    run = symmetrised(policy, env) if symmetrise else policy
    return run_scenarios(env, run, scenarios, seed=seed, estimator=getattr(policy, "estimate", None), command_gain=True)


def ranked_checkpoints(run_dir: Path, spec: str) -> list[Path]:
    """--checkpoints LIST -> checkpoint files of run_dir, in the order given ('all': every
    model_<it>.pt oldest first, then model_best.pt if the run has one); duplicates once."""
    items = [s.strip() for s in spec.split(",") if s.strip()]
    if not items:
        raise UsageError("--checkpoints: give iterations and 'best' separated by commas, or 'all'")
    paths = []
    for item in items:
        if item == "all":
            paths += [p for _, p in common.checkpoints(run_dir)]
            best = run_dir / "model_best.pt"
            paths += [best] if best.is_file() else []
        elif item.isdigit() or item == "best":
            paths.append(common.find_checkpoint(run_dir, item))
        else:
            raise UsageError(f"--checkpoints: {item!r} is neither an iteration, 'best' nor 'all'")
    if not paths:
        raise UsageError(f"--checkpoints {spec}: run {run_dir} has no checkpoint")
    return list(dict.fromkeys(p.resolve() for p in paths))


def rank(args: argparse.Namespace, default_log_root: Path | None) -> int:
    """--checkpoints: every listed checkpoint through the same scenarios (a fresh env each, so
    each result is the one `--checkpoint N` gives), one line each as it goes, then a table
    ordered by falls (fewest first), then checks passed (most first), then iteration."""
    if args.jobs < 1:
        raise UsageError(f"--jobs must be at least 1, got {args.jobs}")
    for flag in ("policy", "checkpoint"):
        if getattr(args, flag):
            raise UsageError(f"--checkpoints ranks checkpoints of a run: leave out --{flag}")
    if args.sim2sim:
        raise UsageError(
            "--checkpoints runs one condition, or the robot-clock check's three with --robot-clock: leave out --sim2sim"
        )
    if args.seeds and not args.robot_clock:
        raise UsageError(
            "--checkpoints runs one seed: leave out --seeds (give --seed N to redraw), or add --robot-clock"
        )
    sel = common.select_checkpoint(args, default_log_root)  # the run, its task and configs
    paths = ranked_checkpoints(sel.run_dir, args.checkpoints)
    scenarios = applicable(SCENARIO_SETS[args.scenarios], sel.spec.env_class, sel.env_cfg)
    if args.robot_clock:
        return rank_robot_clock(args, sel, paths, scenarios)
    cond_name, cond = single_condition(args, sel.env_cfg)
    print(f"[{PROG}] run {sel.run_dir}: {len(paths)} checkpoints, {len(scenarios)} scenarios, {cond_name}")
    rows = []
    work = [(sel, path, scenarios, cond, bool(args.stochastic), args.symmetrise, args.seed) for path in paths]

    def report(done) -> None:  # (row, seconds) per checkpoint, in the order given
        for i, (row, seconds) in enumerate(done, 1):
            rows.append(row)
            print(
                f"[{PROG}] {i}/{len(paths)} {row['file']} (iteration {row['iteration']}): "
                f"{row['passed']}/{row['checks']} checks, {row['falls']} falls ({seconds:.0f} s)",
                flush=True,
            )

    jobs = min(args.jobs, len(paths))
    if jobs == 1:
        report(map(_rank_row, work))
    else:  # each checkpoint in its own process (spawned: no torch or rollout threads forked)
        spawn = multiprocessing.get_context("spawn")
        one_thread = {"initializer": torch.set_num_threads, "initargs": (1,)}  # the processes share the cores
        with concurrent.futures.ProcessPoolExecutor(jobs, mp_context=spawn, **one_thread) as pool:
            report(pool.map(_rank_row, work))
    print()
    print(format_ranking(rows))
    top = min(rows, key=_rank_key)
    print(f"\n[{PROG}] first by this evaluation: {top['file']} (iteration {top['iteration']}): "
          f"{top['passed']}/{top['checks']} checks, {top['falls']} falls")  # fmt: skip
    if args.select:
        write_selection(sel.run_dir, top, rows, args.scenarios, cond_name)
    return common.EXIT_OK


def _rank_row(item) -> tuple[dict, float]:
    """One checkpoint of a --checkpoints ranking in a fresh env: (its row, seconds)."""
    from legged_casters.tools.export import load_actor

    sel, path, scenarios, cond, stochastic, symmetrise, seed = item
    t0 = time.time()
    ckpt = common.load_checkpoint(path)
    env = sel.spec.env_class(eval_env_cfg(sel.env_cfg_for(ckpt), scenarios, condition=cond))
    try:
        policy = checkpoint_policy(load_actor(env, sel.train_cfg, ckpt, path), stochastic)
        results = run_policy(env, policy, scenarios, symmetrise, seed)
    finally:
        env.close()
    checks = verdict(results, sel.task)
    row = {
        "file": path.name, "iteration": _iterations_done(path, ckpt), "passed": sum(ok for _, ok, _ in checks),
        "checks": len(checks), "falls": sum(r.falls for r in results),
        "failed": [f"{_check_label(c)} {v}" for c, ok, v in checks if not ok],
    }  # fmt: skip
    return row, time.time() - t0


def write_selection(run_dir: Path, top: dict, rows: list[dict], scenarios: str, condition: str) -> None:
    """The run's selected.yaml: the chosen checkpoint, why, and every ranked row."""
    record = {
        "file": top["file"],
        "iteration": top["iteration"],
        "why": f"fewest falls ({top['falls']}), then most checks passed ({top['passed']} of {top['checks']}), then "
        f"the newest, of {len(rows)} checkpoints through evaluate.py's '{scenarios}' scenarios ({condition})",
        "ranked": [
            {k: row[k] for k in ("file", "iteration", "passed", "checks", "falls", "failed")}
            for row in sorted(rows, key=_rank_key)
        ],  # fmt: skip
    }
    common.write_text_atomic(run_dir / common.SELECTED_FILE, yaml.safe_dump(record, sort_keys=False))
    print(f"[{PROG}] selected {top['file']}: {run_dir / common.SELECTED_FILE} (play, evaluate and export load it "
          "when no --checkpoint is given)")  # fmt: skip


def resolve_seeds(args: argparse.Namespace) -> list[int]:
    """The seeds of --seed / --seeds; args.seed becomes the first (the one every scenario runs at)."""
    seeds = parse_seeds(args.seeds) if args.seeds else [args.seed]
    if args.seeds and args.seed:
        raise UsageError("give --seed N or --seeds LIST, not both (the list's first seed runs every scenario)")
    args.seed = seeds[0]
    return seeds


def check_redraw(args: argparse.Namespace, seeds: list[int], scenarios) -> None:
    if len(seeds) > 1 and not any(s.random_commands for s in scenarios):
        raise UsageError(f"--seeds: the scenario set {args.scenarios!r} has no random-command scenario to redraw")


def named_conditions(args: argparse.Namespace, env_cfg, names) -> list[tuple[str, dict]]:
    """(name, overrides) of the named rows of SIM2SIM (all of them, or ROBOT_CLOCK)."""
    rows = dict(SIM2SIM)
    return [(name + _seed_note(args), condition_overrides(env_cfg, **rows[name])) for name in names]


def falls_by_seed(spec, env_cfg, cond, scenarios, policy, args: argparse.Namespace, seeds, results) -> dict[int, int]:
    """{seed: falls}: every scenario's at the first seed (`results`), the random-command
    scenarios' again under each further seed."""
    falls = {seeds[0]: sum(r.falls for r in results)}
    if len(seeds) > 1:
        falls.update(redraw_falls(spec, env_cfg, cond, scenarios, policy, args.symmetrise, seeds[1:]))
    return falls


def rank_robot_clock(args: argparse.Namespace, sel, paths: list[Path], scenarios) -> int:
    """--checkpoints with --robot-clock: each checkpoint under the robot-clock check's three conditions (each
    result the one `--checkpoint N --robot-clock` gives), its line as it goes, then the table
    in _robot_clock_key's order."""
    from legged_casters.tools.export import load_actor

    seeds = resolve_seeds(args)
    check_redraw(args, seeds, scenarios)
    conditions = named_conditions(args, sel.env_cfg, ROBOT_CLOCK)
    print(
        f"[{PROG}] run {sel.run_dir}: {len(paths)} checkpoints, {len(scenarios)} scenarios, "
        f"{len(conditions)} conditions (the robot-clock bar), seeds {', '.join(map(str, seeds))}"
    )
    ranked = []
    for i, path in enumerate(paths, 1):
        t0 = time.time()
        ckpt = common.load_checkpoint(path)
        rows, policy = [], None
        for name, cond in conditions:
            env = sel.spec.env_class(eval_env_cfg(sel.env_cfg_for(ckpt), scenarios, condition=cond))
            try:
                if policy is None:
                    policy = checkpoint_policy(load_actor(env, sel.train_cfg, ckpt, path), bool(args.stochastic))
                results = run_policy(env, policy, scenarios, args.symmetrise, args.seed)
            finally:
                env.close()
            falls = falls_by_seed(sel.spec, sel.env_cfg_for(ckpt), cond, scenarios, policy, args, seeds, results)
            rows.append((name, results, verdict(results, sel.task), falls))
        tol = tolerance(rows)[1:]
        row = {
            "file": path.name,
            "iteration": _iterations_done(path, ckpt),
            "passed": sum(ok for _, ok, _ in rows[0][2]),
            "checks": len(rows[0][2]),
            "falls": [sum(r[3].values()) for r in rows],
            "changes": [(t["lin"], t["ang"], t["within"]) for t in tol],  # per condition after the first
            "within": all(t["within"] for t in tol),
        }
        ranked.append(row)
        print(f"[{PROG}] {i}/{len(paths)} {_robot_clock_line(row)} ({time.time() - t0:.0f} s)", flush=True)
    print()
    print(format_robot_clock_ranking(ranked, len(seeds)))
    top = min(ranked, key=_robot_clock_key)
    print(f"\n[{PROG}] first by the robot-clock bar: {_robot_clock_line(top)}")
    return common.EXIT_OK


def _robot_clock_key(row: dict) -> tuple:
    """Fewest falls at the training conditions first (the bar is relative: a checkpoint that
    falls alike everywhere would be within it), then within the bar, then fewest falls in all,
    most checks passed, the newest."""
    return (row["falls"][0], not row["within"], sum(row["falls"]), -row["passed"], -row["iteration"])


def _robot_clock_line(row: dict) -> str:
    falls = " / ".join(map(str, row["falls"]))
    changes = "; ".join(
        f"{name.split(' (')[0]} {lin[0]:+.3f} m/s, {ang[0]:+.3f} rad/s"
        for name, (lin, ang, _) in zip(ROBOT_CLOCK[1:], row["changes"], strict=True)
    )
    return (
        f"{row['file']} (iteration {row['iteration']}): {row['passed']}/{row['checks']} checks, falls {falls}; "
        f"largest changes at {changes}: within {'yes' if row['within'] else 'no'}"
    )


def format_robot_clock_ranking(rows: list[dict], n_seeds: int) -> str:
    """The checkpoints under --robot-clock, best first: checks at the training conditions, falls
    per condition (over every seed), and for each other condition the largest change of an
    error check from the training conditions (m/s; rad/s for wz, with the check) and whether
    that condition is within the bar; then whether all are."""
    names = [n.split(" (")[0] for n in ROBOT_CLOCK]
    lines = [
        f"the robot-clock bar: every error check within {SIM2SIM_TOLERANCE['lin']} m/s "
        f"({SIM2SIM_TOLERANCE['ang']} rad/s for wz) of its training-condition value, and no more falls "
        f"({n_seeds} seed{'s' if n_seeds > 1 else ''})",
        f"| rank | checkpoint | iteration | checks passed | falls ({' / '.join(names)}) | "
        + " | ".join(f"{n}: largest change, m/s; rad/s: within" for n in names[1:])
        + " | within |",
        "|---:|---|---:|---:|---|" + "---|" * (len(names) - 1) + "---|",
    ]
    for k, r in enumerate(sorted(rows, key=_robot_clock_key), 1):
        changes = " | ".join(
            f"{lin[0]:+.3f} ({lin[1]}); {ang[0]:+.3f} ({ang[1]}): {'yes' if ok else 'no'}"
            for lin, ang, ok in r["changes"]
        )
        lines.append(
            f"| {k} | {r['file']} | {r['iteration']} | {r['passed']}/{r['checks']} | "
            f"{' / '.join(map(str, r['falls']))} | {changes} | {'yes' if r['within'] else 'no'} |"
        )
    return "\n".join(lines)


def _iterations_done(path: Path, ckpt: dict) -> int:
    """Iterations trained: the N of model_<N>.pt, else (model_best.pt) the checkpoint's own
    count, which rsl_rl stores as the index of its last iteration (N - 1)."""
    m = common.CHECKPOINT_RE.match(path.name)
    return int(m.group(1)) if m else int(ckpt.get("iter", -2)) + 1


def _check_label(check: str) -> str:
    """A verdict check's short name: 'vx +0.5', 'front_wheel swivel', 'estimator RMS error'."""
    head, _, rest = check.partition(": ")
    if not rest:
        return check.split(" <=")[0]
    if head in ("front_wheel", "rear_wheel"):
        return f"{head} {'swivel' if 'swivel' in rest else 'vx'}"
    if head == "vy slalom":
        return f"{head} {'swing' if 'swing' in rest else 'heading'}"
    return head


def _rank_key(row: dict) -> tuple:
    return (row["falls"], -row["passed"], -row["iteration"])


def format_ranking(rows: list[dict]) -> str:
    lines = ["| rank | checkpoint | iteration | checks passed | falls (all scenarios) | failed checks |",
             "|---:|---|---:|---:|---:|---|"]  # fmt: skip
    for k, r in enumerate(sorted(rows, key=_rank_key), 1):
        failed = "; ".join(r["failed"]) or "-"
        lines.append(
            f"| {k} | {r['file']} | {r['iteration']} | {r['passed']}/{r['checks']} | {r['falls']} | {failed} |"
        )
    return "\n".join(lines)


def evaluate(args: argparse.Namespace, default_log_root: Path | None) -> int:
    if args.symmetrise and args.stochastic:
        raise UsageError("--symmetrise runs the deterministic actor; leave out --stochastic")
    if args.sim2sim and args.robot_clock:
        raise UsageError(f"give --sim2sim ({len(SIM2SIM)} conditions) or --robot-clock (three of them), not both")
    own = "--sim2sim" if args.sim2sim else "--robot-clock" if args.robot_clock else None
    if own and (args.physics_dt or args.action_latency_ms or args.noise or args.imu_bias or args.observation_delay_ms):
        raise UsageError(
            f"{own} runs its own conditions: leave out --physics-dt, --action-latency-ms, --observation-delay-ms, "
            "--noise, --imu-bias"
        )
    if args.select and (not args.checkpoints or args.robot_clock):
        raise UsageError("--select records the first of a --checkpoints ranking under one condition: add "
                         "--checkpoints LIST and leave out --robot-clock")  # fmt: skip
    if args.checkpoints:
        return rank(args, default_log_root)
    seeds = resolve_seeds(args)
    given = Path(args.policy).expanduser() if args.policy else None
    if given is not None and given.suffix == ".pt" and given.is_file() and common.is_training_checkpoint(given):
        if args.load_run or args.checkpoint:
            raise UsageError(f"--policy {given} is a training checkpoint; give it alone or as --checkpoint")
        print(f"[{PROG}] {given} is a training checkpoint: evaluating it from its run {given.parent}")
        args.policy, args.load_run, args.checkpoint = None, str(given.parent), str(given)
    if args.policy:
        if args.stochastic:
            raise UsageError("--stochastic needs a training checkpoint (an exported policy is deterministic)")
        if args.load_run or args.checkpoint:
            raise UsageError(
                "--policy evaluates an exported policy; --load_run/--checkpoint choose a training run: pick one"
            )
        task, spec, env_cfg, policy, label, dim = load_exported(Path(args.policy).expanduser(), args.task)
    else:
        dim = None
        try:
            sel = common.select_checkpoint(args, default_log_root)
        except UsageError as err:
            shipped = common.shipped_policy_dir(args.task or common.default_task())
            if args.load_run or args.checkpoint or args.experiment_name or shipped is None:
                raise err from None
            if args.stochastic:
                raise UsageError(
                    "--stochastic needs a training checkpoint; no run was found (train one first)"
                ) from None
            print(f"[{PROG}] no run found: evaluating the shipped policy {shipped}")
            # under the task its policy.yaml names (the shipped caster_omni: caster_omni_sym)
            task, spec, env_cfg, policy, label, dim = load_exported(shipped, None)
            sel = None
        if sel is not None:
            from legged_casters.tools.export import load_actor

            task, spec, env_cfg = sel.task, sel.spec, sel.env_cfg
            probe = spec.env_class(eval_env_cfg(env_cfg, QUICK[:1]))
            actor = load_actor(probe, sel.train_cfg, sel.ckpt, sel.ckpt_path)
            probe.close()
            policy = checkpoint_policy(actor, bool(args.stochastic))
            label = f"{sel.ckpt_path}" + (" (stochastic)" if args.stochastic else "")
    if args.symmetrise:
        label += " (symmetrised)"
    scenarios = applicable(SCENARIO_SETS[args.scenarios], spec.env_class, env_cfg)
    check_redraw(args, seeds, scenarios)
    if args.sim2sim:
        conditions = named_conditions(args, env_cfg, [name for name, _ in SIM2SIM])
    elif args.robot_clock:
        conditions = named_conditions(args, env_cfg, ROBOT_CLOCK)
    else:
        conditions = [single_condition(args, env_cfg)]
    rows = []
    for name, cond in conditions:
        env = spec.env_class(eval_env_cfg(env_cfg, scenarios, condition=cond))
        if dim is not None and dim != env.observation_dims()["policy"]:
            env.close()
            raise common.CheckpointError(
                f"{label} expects {dim} observations; task {task} as configured gives "
                f"{env.observation_dims()['policy']}"
            )
        print(f"[{PROG}] {label}: task {task}, {len(scenarios)} scenarios on {env.num_envs} envs; {name}")
        t0 = time.time()
        try:
            results = run_policy(env, policy, scenarios, args.symmetrise, args.seed)
        finally:
            env.close()
        print(format_table(results))
        checks = verdict(results, task)
        passed = sum(ok for _, ok, _ in checks)
        print()
        for check, ok, value in checks:
            print(f"{'PASS' if ok else 'FAIL'}  {check}  (measured {value})")
        print(f"\n[{PROG}] verdict: {passed}/{len(checks)} checks passed ({time.time() - t0:.0f} s); {name}")
        falls = falls_by_seed(spec, env_cfg, cond, scenarios, policy, args, seeds, results)
        rows.append((name, results, checks, falls))
    if len(seeds) > 1:
        print()
        print(format_seed_falls(rows, seeds))
    if len(rows) > 1:
        print()
        print(format_sim2sim(rows))
        if args.sim2sim or args.robot_clock:
            print()
            print(format_tolerance(rows, len(seeds)))
    return common.EXIT_OK


def redraw_falls(spec, env_cfg, cond, scenarios, policy, symmetrise: bool, seeds) -> dict[int, int]:
    """{seed: falls} of `scenarios`' random-command scenarios under each further seed, on the
    whole set's ground, one env for all seeds. Under conditions without random draws of their
    own (all but noise and IMU bias) each count is the one `--seed N` gives."""
    redrawn = tuple(s for s in scenarios if s.random_commands)
    names = ", ".join(s.name for s in redrawn)
    env = spec.env_class(eval_env_cfg(env_cfg, redrawn, condition=cond, terrain_of=scenarios))
    out = {}
    try:
        for seed in seeds:
            t0 = time.time()
            out[seed] = sum(r.falls for r in run_policy(env, policy, redrawn, symmetrise, seed))
            print(f"[{PROG}] seed {seed}: {names}: {out[seed]} falls ({time.time() - t0:.0f} s)", flush=True)
    finally:
        env.close()
    return out


def format_seed_falls(rows, seeds: list[int]) -> str:
    """Falls per seed and condition: at the first seed in every scenario, at the others in the
    random-command scenarios (the rest do not depend on the seed)."""
    lines = ["| condition | " + " | ".join(f"seed {k}" for k in seeds) + " | total |",
             "|---|" + "---:|" * (len(seeds) + 1)]  # fmt: skip
    for name, _, _, falls in rows:
        lines.append(f"| {name} | " + " | ".join(str(falls[k]) for k in seeds) + f" | {sum(falls.values())} |")
    return "\n".join(lines)


def error_checks(checks) -> dict[str, tuple[str, float]]:
    """The verdict's checks that measure an error: {check: ("lin" (m/s) or "ang" (rad/s), value)}."""
    out = {}
    for check, _, value in checks:
        if "error" in check:
            out[check] = ("ang" if "|wz error|" in check else "lin", float(value.split()[0]))
    return out


def tolerance(rows) -> list[dict]:
    """Each condition of `rows` (name, results, checks, {seed: falls}) against the first under
    SIM2SIM_TOLERANCE: the largest change of an error check, m/s and rad/s apart, as
    (change, check), the falls over all seeds, and whether it is within."""
    base = error_checks(rows[0][2])
    base_falls = sum(rows[0][3].values())
    tol = SIM2SIM_TOLERANCE
    out = []
    for name, _, checks, falls in rows:
        worst = {"lin": (0.0, "-"), "ang": (0.0, "-")}
        for check, (kind, value) in error_checks(checks).items():
            if check in base:
                d = value - base[check][1]
                if abs(d) > abs(worst[kind][0]):
                    worst[kind] = (d, _check_label(check))
        total = sum(falls.values())
        ok = abs(worst["lin"][0]) <= tol["lin"] and abs(worst["ang"][0]) <= tol["ang"] and total <= base_falls
        out.append({"name": name, "lin": worst["lin"], "ang": worst["ang"], "falls": total, "within": ok})
    return out


def format_tolerance(rows, n_seeds: int) -> str:
    """tolerance() as a table, with the bar it applies."""
    tol = SIM2SIM_TOLERANCE
    lines = [
        f"sim-to-sim tolerance: every error check within {tol['lin']} m/s ({tol['ang']} rad/s for wz) of the first "
        f"condition's, and no more falls ({n_seeds} seed{'s' if n_seeds > 1 else ''})",
        "| condition | largest change, m/s | largest change, rad/s | falls | within |",
        "|---|---|---|---:|---|",
    ]
    for t in tolerance(rows):
        lines.append(
            f"| {t['name']} | {t['lin'][0]:+.3f} ({t['lin'][1]}) | {t['ang'][0]:+.3f} ({t['ang'][1]}) | "
            f"{t['falls']} | {'yes' if t['within'] else 'no'} |"
        )
    return "\n".join(lines)


def format_sim2sim(rows) -> str:
    """One line per condition: checks passed, falls, and the largest change of a tracking
    error from the first row (m/s for vx/vy, rad/s for wz) with the scenario it is in."""
    base = {r.name: r for r in rows[0][1]}
    lines = [
        "| condition | checks passed | falls (first seed) | largest change of a vx/vy error (m/s) "
        "| of a wz error (rad/s) |",
        "|---|---:|---:|---|---|",
    ]
    for name, results, checks, _ in rows:
        changes = {"lin": [], "ang": []}
        for r in results:
            if r.name in base and r.kind in ("track", "mode"):
                for axis in ("vx", "vy", "wz"):
                    d = r.err[axis] - base[r.name].err[axis]
                    if d:
                        changes["ang" if axis == "wz" else "lin"].append((d, f"{r.name} {axis}"))
        lin, ang = (max(changes[k], key=lambda c: abs(c[0]), default=(0.0, "-")) for k in ("lin", "ang"))
        falls = sum(r.falls for r in results)
        lines.append(
            f"| {name} | {sum(ok for _, ok, _ in checks)}/{len(checks)} | {falls} | "
            f"{lin[0]:+.3f} ({lin[1]}) | {ang[0]:+.3f} ({ang[1]}) |"
        )
    return "\n".join(lines)


def main(argv: list[str] | None = None, default_log_root: Path | str | None = None) -> int:
    args = build_parser().parse_args(argv)
    return common.run_cli(
        lambda: evaluate(args, Path(default_log_root) if default_log_root else None), PROG, args.verbose
    )


if __name__ == "__main__":
    sys.exit(main())
