"""Driving by hand: stick and button states -> operator commands, with no I/O.

Two sources use it (docs/driving.md):

* a Linux gamepad read through the kernel joystick API (``/dev/input/js*``), in
  ``teleop --gamepad``: `JsEvent` decodes its 8-byte events, `Gamepad` keeps the state
  and turns it into a `Drive` decision;
* the Go2's own remote, which the robot reports in ``LowState.wireless_remote``, in
  ``go2_adapter --remote``: `RemoteState` decodes those 40 bytes, `Remote` turns them
  into a decision.

Both share the rules: each stick axis has a dead zone (released sticks give exactly
zero) and is scaled to the task's command range, then clamped inside it
(`CommandRanges`: the ranges the policy was trained with, read from its run's
configuration); a stop latches until a reset, and a stop pressed together with a reset
is a stop; propulsion modes are chosen with buttons and kept.
"""

from __future__ import annotations

import math
import struct
from dataclasses import dataclass, field
from pathlib import Path

from legged_casters.deploy import protocol as P

DEFAULT_DEAD_ZONE = 0.1
"""Fraction of a stick's travel around its centre that counts as released."""


# --- command ranges ----------------------------------------------------------------------
@dataclass(frozen=True)
class CommandRanges:
    """(lo, hi) of vx, vy (m/s) and wz (rad/s) that a hand-driven command may reach."""

    vx: tuple[float, float]
    vy: tuple[float, float]
    wz: tuple[float, float]

    def __post_init__(self):
        for name in ("vx", "vy", "wz"):
            lo, hi = (float(v) for v in getattr(self, name))
            if not (math.isfinite(lo) and math.isfinite(hi) and lo <= hi):
                raise ValueError(f"command range {name} = ({lo}, {hi}) is not an interval")

    @classmethod
    def from_limits(cls, limits) -> CommandRanges:
        """From [(lo, hi) of vx, vy, wz] (CommandsCfg.limits())."""
        vx, vy, wz = (tuple(float(v) for v in lim) for lim in limits)
        return cls(vx, vy, wz)

    def as_tuples(self) -> tuple[tuple[float, float], ...]:
        return self.vx, self.vy, self.wz

    def scale(self, s: float, axis: int) -> float:
        """A stick value in [-1, 1] (after its dead zone) -> a command on `axis` (0 vx, 1 vy,
        2 wz): +1 reaches the range's upper end, -1 its lower end, 0 is 0; the result
        lies inside the range (or is 0 when the range does not contain 0)."""
        lo, hi = self.as_tuples()[axis]
        v = s * max(hi, 0.0) if s > 0 else -s * min(lo, 0.0)
        return min(max(v, min(lo, 0.0)), max(hi, 0.0))

    def capped(self, limits) -> CommandRanges:
        """These ranges narrowed to +-limits (|vx|, |vy|, |wz|; never widened)."""
        out = []
        for (lo, hi), lim in zip(self.as_tuples(), limits, strict=True):
            lim = abs(float(lim))
            out.append((min(max(lo, -lim), lim), min(max(hi, -lim), lim)))
        return CommandRanges(*out)

    def describe(self) -> str:
        return ", ".join(
            f"{n} [{lo:g}, {hi:g}]" for n, (lo, hi) in zip(("vx", "vy", "wz"), self.as_tuples(), strict=True)
        )


def task_command_ranges(task: str) -> CommandRanges:
    """The command ranges a registered task trains with by default."""
    from legged_casters import registry

    try:
        env_cfg, _ = registry.task_configs(task)
    except registry.UnknownTaskError as err:
        raise ValueError(str(err)) from None
    return CommandRanges.from_limits(env_cfg.commands.limits())


def policy_limits(policy: str | Path) -> tuple[CommandRanges, tuple[P.PropulsionMode, ...]]:
    """The command ranges an exported policy was trained with and its propulsion modes: its
    task in policy.yaml, the ranges in the env.yaml next to it or in its run directory
    (what play.py and evaluate.py use), else the task's defaults; the modes of its
    policy.yaml (none listed: four_wheel only, as the bridge takes it). `policy`: the
    export directory or one of its files."""
    from legged_casters import registry
    from legged_casters.config import ConfigError
    from legged_casters.tools.common import UsageError, read_export

    path = Path(policy)
    if path.is_dir():
        path = path / "policy.yaml"
    if not path.with_suffix(".yaml").is_file():
        raise ValueError(f"{path.with_suffix('.yaml')} does not exist: --policy wants an export directory")
    try:
        export = read_export(path.with_suffix(".pt"), None)
    except (UsageError, ConfigError, registry.UnknownTaskError) as err:
        raise ValueError(str(err)) from None
    listed = export.meta.get("propulsion_modes") or {}
    modes = tuple(m for m in P.PropulsionMode if m.key in listed) or (P.PropulsionMode.FOUR_WHEEL,)
    return CommandRanges.from_limits(export.env_cfg.commands.limits()), modes


def add_drive_args(p) -> None:
    """--policy / --task / --max-command / --dead-zone on an argparse parser: what bounds
    hand driving."""
    g = p.add_mutually_exclusive_group()
    g.add_argument("--policy", help="export directory whose training command ranges bound the sticks")
    g.add_argument("--task", help="task whose default command ranges bound the sticks")
    p.add_argument(
        "--max-command",
        type=float,
        nargs=3,
        metavar=("VX", "VY", "WZ"),
        help="narrow the ranges further to +-these (m/s, m/s, rad/s)",
    )
    p.add_argument(
        "--dead-zone",
        type=float,
        default=DEFAULT_DEAD_ZONE,
        help=f"stick travel around the centre read as released (default {DEFAULT_DEAD_ZONE})",
    )


def drive_limits(args) -> tuple[CommandRanges, tuple[P.PropulsionMode, ...], str]:
    """(ranges, modes, where they came from) of --policy / --task, capped by --max-command;
    ValueError when they cannot be read."""
    if not 0.0 <= args.dead_zone < 1.0:
        raise ValueError(f"--dead-zone {args.dead_zone}: must be in [0, 1)")
    if args.policy:
        ranges, modes = policy_limits(args.policy)
        source = f"policy {args.policy}"
    else:
        ranges, modes = task_command_ranges(args.task), tuple(P.PropulsionMode)
        source = f"task {args.task}"
    if args.max_command is not None:
        ranges = ranges.capped(args.max_command)
    return ranges, modes, source


def dead_zone(value: float, zone: float) -> float:
    """A raw stick value in [-1, 1] -> 0 inside +-zone, else rescaled so that the edge of
    the zone is 0 and the end of travel is +-1; non-finite values read as 0."""
    if not math.isfinite(value):
        return 0.0
    v = min(max(float(value), -1.0), 1.0)
    if abs(v) <= zone:
        return 0.0
    return math.copysign((abs(v) - zone) / (1.0 - zone), v)


def sticks_to_velocity(forward: float, left: float, turn_left: float, ranges: CommandRanges, zone: float):
    """Stick values (+1: full forward / full left / full counter-clockwise) -> (vx, vy, wz)."""
    return tuple(ranges.scale(dead_zone(s, zone), k) for k, s in enumerate((forward, left, turn_left)))


# --- the decision both sources make ----------------------------------------------------------
@dataclass
class Drive:
    """What a hand-driven source asks for now."""

    vx: float = 0.0
    vy: float = 0.0
    wz: float = 0.0
    propulsion: P.PropulsionMode = P.PropulsionMode.FOUR_WHEEL
    stop: bool = False
    """A stop is latched: every message carries the stop flag (and zero velocity)."""
    reset: bool = False
    """A reset was asked for (the flag goes out on the next messages)."""

    @property
    def flags(self) -> int:
        return P.OP_STOP if self.stop else (P.OP_RESET if self.reset else 0)

    def command(self, header: P.Header | None = None) -> P.OperatorCommand:
        return P.OperatorCommand(self.vx, self.vy, self.wz, self.propulsion, self.flags, header or P.Header())


@dataclass
class Latch:
    """The stop / reset rule shared by the sources: a stop press latches the stop (and
    zeroes the velocity); a reset press, with no stop pressed, releases it and raises the
    reset flag for `reset_messages` messages."""

    reset_messages: int = 3
    stopped: bool = False
    _reset_left: int = 0

    def update(self, stop_pressed: bool, reset_pressed: bool) -> None:
        if stop_pressed:
            self.stopped, self._reset_left = True, 0
        elif reset_pressed:
            self.stopped, self._reset_left = False, self.reset_messages

    def take_reset(self) -> bool:
        """Whether the next message carries the reset flag (counts it down)."""
        if self._reset_left > 0:
            self._reset_left -= 1
            return True
        return False


# --- Linux gamepad ---------------------------------------------------------------------------
JS_EVENT = struct.Struct("<IhBB")
"""struct js_event (linux/joystick.h): u32 time (ms), s16 value, u8 type, u8 number."""
JS_BUTTON, JS_AXIS, JS_INIT = 0x01, 0x02, 0x80


@dataclass(frozen=True)
class JsEvent:
    time_ms: int
    value: int
    type: int
    number: int

    @classmethod
    def decode(cls, buf: bytes) -> JsEvent:
        return cls(*JS_EVENT.unpack(buf))

    def encode(self) -> bytes:
        return JS_EVENT.pack(self.time_ms & 0xFFFFFFFF, self.value, self.type, self.number)

    @classmethod
    def axis(cls, number: int, value: float, time_ms: int = 0) -> JsEvent:
        """An axis event of a value in [-1, 1] (tests)."""
        return cls(time_ms, max(-32767, min(32767, round(value * 32767))), JS_AXIS, number)

    @classmethod
    def button(cls, number: int, pressed: bool, time_ms: int = 0) -> JsEvent:
        return cls(time_ms, int(pressed), JS_BUTTON, number)


def decode_js_events(buf: bytes) -> tuple[list[JsEvent], bytes]:
    """Whole events in `buf` and the bytes left over (a partial event)."""
    n = len(buf) // JS_EVENT.size
    return [JsEvent.decode(buf[k * JS_EVENT.size : (k + 1) * JS_EVENT.size]) for k in range(n)], buf[
        n * JS_EVENT.size :
    ]


@dataclass(frozen=True)
class GamepadMap:
    """Which axis / button does what. The defaults fit an Xbox-style pad under Linux's xpad
    driver (axes: 0 left x, 1 left y, 3 right x; buttons: 0 A, 1 B, 2 X, 3 Y, 7 start);
    the kernel reports an axis pushed up or right as positive on x and negative on y."""

    forward_axis: int = 1
    """Left stick up/down -> vx (the kernel reports up as negative: inverted)."""
    left_axis: int = 0
    """Left stick left/right -> vy (right is positive in the kernel: inverted)."""
    turn_axis: int = 3
    """Right stick left/right -> wz (right is positive in the kernel: inverted)."""
    stop_button: int = 1  # B
    reset_button: int = 7  # start
    mode_buttons: tuple[tuple[int, P.PropulsionMode], ...] = (
        (2, P.PropulsionMode.FOUR_WHEEL),  # X
        (3, P.PropulsionMode.FRONT_WHEEL),  # Y
        (0, P.PropulsionMode.REAR_WHEEL),  # A
    )

    def describe(self) -> str:
        modes = ", ".join(f"button {b} {m.key}" for b, m in self.mode_buttons)
        return (
            f"axis {self.forward_axis} vx, axis {self.left_axis} vy, axis {self.turn_axis} wz; button "
            f"{self.stop_button} stop, button {self.reset_button} reset; {modes}"
        )


@dataclass
class Gamepad:
    """A gamepad's axes and buttons as its events report them, and what they ask for."""

    ranges: CommandRanges
    mapping: GamepadMap = field(default_factory=GamepadMap)
    zone: float = DEFAULT_DEAD_ZONE
    propulsion: P.PropulsionMode = P.PropulsionMode.FOUR_WHEEL
    modes: tuple[P.PropulsionMode, ...] = tuple(P.PropulsionMode)
    """The modes the policy has (a mode button for another one is ignored)."""
    axes: dict[int, float] = field(default_factory=dict)
    buttons: dict[int, bool] = field(default_factory=dict)
    latch: Latch = field(default_factory=Latch)

    def apply(self, ev: JsEvent) -> None:
        """One event (the initial-state events the driver sends on open included)."""
        kind = ev.type & ~JS_INIT
        if kind == JS_AXIS:
            self.axes[ev.number] = max(-1.0, min(1.0, ev.value / 32767.0))
        elif kind == JS_BUTTON:
            pressed = bool(ev.value)
            was = self.buttons.get(ev.number, False)
            self.buttons[ev.number] = pressed
            if pressed and not was:
                if not ev.type & JS_INIT:
                    self._pressed(ev.number)
                elif ev.number == self.mapping.stop_button:  # held down when the device opened
                    self.latch.update(True, False)

    def _pressed(self, number: int) -> None:
        m = self.mapping
        stop = number == m.stop_button or self.buttons.get(m.stop_button, False)
        self.latch.update(stop, number == m.reset_button)
        for button, mode in m.mode_buttons:
            if number == button and mode in self.modes:
                self.propulsion = mode

    def drive(self) -> Drive:
        """What to send now: zero velocity while stopped; sticks inside their dead zone
        give exactly zero."""
        a, m = self.axes, self.mapping
        if self.latch.stopped:
            return Drive(propulsion=self.propulsion, stop=True)
        vx, vy, wz = sticks_to_velocity(
            -a.get(m.forward_axis, 0.0), -a.get(m.left_axis, 0.0), -a.get(m.turn_axis, 0.0), self.ranges, self.zone
        )
        return Drive(vx, vy, wz, self.propulsion, reset=self.latch.take_reset())


# --- the Go2's remote -------------------------------------------------------------------------
# LowState.wireless_remote, 40 bytes, as unitree_sdk2's example/state_machine/gamepad.hpp
# (xRockerBtnDataStruct; the Go2 LowState_ example robot_controller.hpp copies the 40 bytes
# into it) lays them out, little-endian: head[2] at 0, the button bitfield xKeySwitchUnion
# (uint16) at 2, then float lx at 4, rx at 8, ry at 12, L2 at 16, ly at 20, idle[16] at 24.
# The same offsets are read by unitree_rl_gym's deploy/deploy_real/common/remote_controller.py.
REMOTE_SIZE = 40  # unitree.WIRELESS_REMOTE_SIZE
REMOTE_LAYOUT = struct.Struct("<2BH5f16x")
REMOTE_BUTTONS = tuple(
    ["R1", "L1", "start", "select", "R2", "L2", "F1", "F2", "A", "B", "X", "Y", "up", "right", "down", "left"]
)
"""xKeySwitchUnion's bits, least significant first (GCC allocates bit-fields from bit 0 up)."""
REMOTE_BIT = {name: 1 << k for k, name in enumerate(REMOTE_BUTTONS)}


@dataclass(frozen=True)
class RemoteState:
    """The remote's sticks (lx, ly, rx, ry in [-1, 1]: right / up positive) and buttons."""

    buttons: int = 0
    lx: float = 0.0
    rx: float = 0.0
    ry: float = 0.0
    l2: float = 0.0
    ly: float = 0.0
    present: bool = True
    """False for 40 zero bytes: nothing was received from a remote."""

    @classmethod
    def decode(cls, raw) -> RemoteState:
        raw = bytes(raw)
        if len(raw) != REMOTE_SIZE:
            raise ValueError(f"wireless_remote has {len(raw)} bytes, expected {REMOTE_SIZE}")
        _, _, buttons, lx, rx, ry, l2, ly = REMOTE_LAYOUT.unpack(raw)
        return cls(buttons, lx, rx, ry, l2, ly, present=any(raw))

    @classmethod
    def encode(cls, pressed=(), lx=0.0, rx=0.0, ry=0.0, ly=0.0, l2=0.0, head=(0x55, 0xAA)) -> bytes:
        """40 bytes as the robot would report them (tests, the fake Go2)."""
        bits = 0
        for name in pressed:
            bits |= REMOTE_BIT[name]
        return REMOTE_LAYOUT.pack(*head, bits, lx, rx, ry, l2, ly)

    def pressed(self, *names: str) -> bool:
        """All of these buttons are down."""
        return all(self.buttons & REMOTE_BIT[n] for n in names)


@dataclass(frozen=True)
class RemoteMap:
    """Button combinations of the Go2's remote; sticks: left up/down vx, left left/right vy,
    right left/right wz (the convention of Unitree's own examples)."""

    stop: tuple[str, ...] = ("L2", "B")
    reset: tuple[str, ...] = ("L2", "start")
    modes: tuple[tuple[tuple[str, ...], P.PropulsionMode], ...] = (
        (("X",), P.PropulsionMode.FOUR_WHEEL),
        (("Y",), P.PropulsionMode.FRONT_WHEEL),
        (("A",), P.PropulsionMode.REAR_WHEEL),
    )

    def describe(self) -> str:
        modes = ", ".join(f"{'+'.join(b)} {m.key}" for b, m in self.modes)
        return f"{'+'.join(self.stop)} stop (damping), {'+'.join(self.reset)} reset; {modes}"


@dataclass
class Remote:
    """The Go2 remote's state -> a decision. A combination acts on the sample where it
    becomes fully pressed; the stop wins over anything pressed with it."""

    ranges: CommandRanges
    mapping: RemoteMap = field(default_factory=RemoteMap)
    zone: float = DEFAULT_DEAD_ZONE
    propulsion: P.PropulsionMode = P.PropulsionMode.FOUR_WHEEL
    modes: tuple[P.PropulsionMode, ...] = tuple(P.PropulsionMode)
    latch: Latch = field(default_factory=Latch)
    last: RemoteState = field(default_factory=lambda: RemoteState(present=False))

    @property
    def stopped(self) -> bool:
        return self.latch.stopped

    def update(self, state: RemoteState) -> None:
        m, before = self.mapping, self.last
        self.last = state
        if not state.present:
            return
        stop = state.pressed(*m.stop)  # held, not only on the edge: a held stop keeps it latched
        reset = state.pressed(*m.reset) and not before.pressed(*m.reset)
        if stop or reset:
            self.latch.update(stop, reset)
        if stop:
            return
        for names, mode in m.modes:
            if state.pressed(*names) and not before.pressed(*names) and mode in self.modes:
                self.propulsion = mode

    def drive(self) -> Drive:
        s = self.last
        if self.latch.stopped:
            return Drive(propulsion=self.propulsion, stop=True)
        if not s.present:
            return Drive(propulsion=self.propulsion)
        # lx / rx: right positive -> vy / wz: left / counter-clockwise positive
        vx, vy, wz = sticks_to_velocity(s.ly, -s.lx, -s.rx, self.ranges, self.zone)
        return Drive(vx, vy, wz, self.propulsion, reset=self.latch.take_reset())
