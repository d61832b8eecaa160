"""Driving by keyboard: key presses -> operator commands, with no I/O (``play.py --drive``).

The keys follow the rules of the gamepad and the Go2 remote (`legged_casters.deploy.drive`):
each press moves one axis a step of its range (`STEPS` presses from zero to the end), the
value is scaled to the task's command ranges and clamped inside them (`CommandRanges`);
the stop key zeroes every axis at once and latches until the reset key, which also asks
for the robot to be reset; propulsion modes are chosen with number keys and kept.

Keys are named as `KEY_MAP` spells them ("w", "up", "space", "1"); the viewers translate
their own key codes with `glfw_key_name` (MuJoCo's desktop viewer) or the ImGui key names
(the browser viewer).
"""

from __future__ import annotations

from dataclasses import dataclass, field

from legged_casters.deploy import protocol as P
from legged_casters.deploy.drive import CommandRanges, Drive, Latch

STEPS = 10
"""Presses that take an axis from zero to the end of its range."""

AXES = ("vx", "vy", "wz")

KEY_MAP: dict[str, tuple[int, int]] = {
    "w": (0, +1),
    "up": (0, +1),
    "s": (0, -1),
    "down": (0, -1),
    "a": (1, +1),
    "d": (1, -1),
    "q": (2, +1),
    "left": (2, +1),
    "e": (2, -1),
    "right": (2, -1),
}
"""Key -> (axis, direction): vx forward +, vy left +, wz counter-clockwise +."""
STOP_KEY = "space"
RESET_KEY = "r"
MODE_KEYS: dict[str, P.PropulsionMode] = {
    "1": P.PropulsionMode.FOUR_WHEEL,
    "2": P.PropulsionMode.FRONT_WHEEL,
    "3": P.PropulsionMode.REAR_WHEEL,
}
KEYS = (*KEY_MAP, STOP_KEY, RESET_KEY, *MODE_KEYS)
"""Every key the keyboard driver reads."""

HELP = (
    "W/S or Up/Down: vx +/-; A/D: vy left/right; Q/E or Left/Right: turn left/right; "
    "1/2/3: four_wheel/front_wheel/rear_wheel; Space: stop (zero, held until R); R: reset"
)


@dataclass
class Keyboard:
    """The keys pressed so far and what they ask for."""

    ranges: CommandRanges
    steps: int = STEPS
    propulsion: P.PropulsionMode = P.PropulsionMode.FOUR_WHEEL
    modes: tuple[P.PropulsionMode, ...] = tuple(P.PropulsionMode)
    """The modes the policy has (a key for another one is ignored)."""
    latch: Latch = field(default_factory=lambda: Latch(reset_messages=1))
    level: list[int] = field(default_factory=lambda: [0, 0, 0])
    """Steps of each axis, in [-steps, steps]."""

    def __post_init__(self):
        if self.steps < 1:
            raise ValueError(f"steps must be at least 1, got {self.steps}")

    def press(self, key: str) -> bool:
        """One key press (a key name of `KEYS`, case-insensitive); whether the key is one
        the driver reads."""
        key = key.lower()
        if key == STOP_KEY:
            self.latch.update(True, False)
            self.level = [0, 0, 0]
        elif key == RESET_KEY:
            self.latch.update(False, True)
            self.level = [0, 0, 0]
        elif key in MODE_KEYS:
            if MODE_KEYS[key] in self.modes and not self.latch.stopped:
                self.propulsion = MODE_KEYS[key]
        elif key in KEY_MAP:
            if not self.latch.stopped:  # a stop holds until the reset key
                axis, sign = KEY_MAP[key]
                self.level[axis] = max(-self.steps, min(self.steps, self.level[axis] + sign))
        else:
            return False
        return True

    def velocity(self) -> tuple[float, float, float]:
        """(vx, vy, wz) now: zero while stopped, else inside the ranges."""
        if self.latch.stopped:
            return 0.0, 0.0, 0.0
        return tuple(self.ranges.scale(self.level[k] / self.steps, k) for k in range(3))

    def drive(self) -> Drive:
        """What to send now (the reset flag once after the reset key)."""
        if self.latch.stopped:
            return Drive(propulsion=self.propulsion, stop=True)
        return Drive(*self.velocity(), self.propulsion, reset=self.latch.take_reset())


# --- key codes of the viewers ------------------------------------------------------------------
_GLFW_NAMES = {32: "space", 262: "right", 263: "left", 264: "down", 265: "up"}


def glfw_key_name(code: int) -> str | None:
    """A GLFW key code (what MuJoCo's desktop viewer passes to its key_callback) -> the
    key's name in `KEYS`, or None for a key the driver does not read."""
    if code in _GLFW_NAMES:
        return _GLFW_NAMES[code]
    if 32 < code < 127:
        name = chr(code).lower()
        return name if name in KEYS else None
    return None


def imgui_key_attr(name: str) -> str:
    """A key name of `KEYS` -> the attribute of ImGui's Key enum that reports it
    (``imgui.Key.W``, ``imgui.Key.UpArrow``, ``imgui.Key.N1``, ``imgui.Key.Space``)."""
    arrows = {"up": "UpArrow", "down": "DownArrow", "left": "LeftArrow", "right": "RightArrow"}
    if name in arrows:
        return arrows[name]
    if name == "space":
        return "Space"
    if name.isdigit():
        return f"N{name}"
    return name.upper()
