"""Driving by keyboard (play.py --drive): the key mapping of legged_casters.deploy.keyboard."""

from __future__ import annotations

import pytest

from legged_casters.deploy import drive, keyboard
from legged_casters.deploy import protocol as P

RANGES = drive.CommandRanges((-0.5, 1.0), (-0.4, 0.4), (-1.2, 1.2))


def _inside(v, ranges=RANGES) -> bool:
    return all(lo <= x <= hi for x, (lo, hi) in zip(v, ranges.as_tuples(), strict=True))


def test_each_press_steps_an_axis_and_never_leaves_the_ranges():
    kb = keyboard.Keyboard(RANGES, steps=4)
    assert kb.velocity() == (0.0, 0.0, 0.0)
    kb.press("w")
    assert kb.velocity() == pytest.approx((0.25, 0.0, 0.0))
    for _ in range(20):  # held far past the end: stays at the top of the range
        kb.press("up")
    assert kb.velocity()[0] == pytest.approx(1.0)
    for _ in range(40):
        kb.press("S")  # case-insensitive
        kb.press("a")
        kb.press("e")
        assert _inside(kb.velocity())
    assert kb.velocity() == pytest.approx((-0.5, 0.4, -1.2))
    for key in ("d", "q", "left", "right", "down"):
        kb.press(key)
        assert _inside(kb.velocity())


def test_asymmetric_and_one_sided_ranges():
    ranges = drive.CommandRanges((0.0, 2.0), (0.0, 0.0), (-0.5, 1.0))
    kb = keyboard.Keyboard(ranges, steps=2)
    for _ in range(5):
        kb.press("s")  # no backward range: stays 0
        kb.press("d")  # no sideways range
        kb.press("e")
    assert kb.velocity() == pytest.approx((0.0, 0.0, -0.5))


def test_stop_zeroes_at_once_and_holds_until_reset():
    kb = keyboard.Keyboard(RANGES)
    for key in ("w", "w", "a", "q"):
        kb.press(key)
    assert kb.velocity() != (0.0, 0.0, 0.0)
    kb.press("space")
    d = kb.drive()
    assert d.stop and (d.vx, d.vy, d.wz) == (0.0, 0.0, 0.0) and d.flags == P.OP_STOP
    for key in ("w", "a", "q", "2"):  # ignored while stopped
        kb.press(key)
    assert kb.drive().stop and kb.velocity() == (0.0, 0.0, 0.0)
    assert kb.propulsion == P.PropulsionMode.FOUR_WHEEL
    kb.press("r")  # releases the stop, asks once for a reset, from zero
    d = kb.drive()
    assert not d.stop and d.reset and (d.vx, d.vy, d.wz) == (0.0, 0.0, 0.0)
    assert not kb.drive().reset
    kb.press("w")
    assert kb.velocity()[0] > 0


def test_mode_keys_only_pick_the_policys_modes():
    kb = keyboard.Keyboard(RANGES, modes=(P.PropulsionMode.FOUR_WHEEL, P.PropulsionMode.REAR_WHEEL))
    kb.press("2")  # front_wheel: not a mode of this policy
    assert kb.propulsion == P.PropulsionMode.FOUR_WHEEL
    kb.press("3")
    assert kb.drive().propulsion == P.PropulsionMode.REAR_WHEEL
    kb.press("1")
    assert kb.propulsion == P.PropulsionMode.FOUR_WHEEL
    none = keyboard.Keyboard(RANGES, modes=())
    none.press("2")
    assert none.propulsion == P.PropulsionMode.FOUR_WHEEL


def test_unknown_keys_are_ignored():
    kb = keyboard.Keyboard(RANGES)
    assert not kb.press("x") and not kb.press("f1")
    assert kb.velocity() == (0.0, 0.0, 0.0)
    with pytest.raises(ValueError):
        keyboard.Keyboard(RANGES, steps=0)


def test_viewer_key_codes():
    # GLFW codes as MuJoCo's desktop viewer reports them
    assert keyboard.glfw_key_name(ord("W")) == "w" and keyboard.glfw_key_name(32) == "space"
    assert keyboard.glfw_key_name(265) == "up" and keyboard.glfw_key_name(263) == "left"
    assert keyboard.glfw_key_name(ord("1")) == "1" and keyboard.glfw_key_name(ord("X")) is None
    assert keyboard.glfw_key_name(290) is None  # F1
    # every key has an ImGui name (the browser viewer)
    imgui = pytest.importorskip("mujoco.studio.dear_imgui.dear_imgui")
    for name in keyboard.KEYS:
        assert hasattr(imgui.Key, keyboard.imgui_key_attr(name)), name


@pytest.mark.parametrize(
    "extra",
    [["--profile", "steps"], ["--cmd", "1", "0", "0"], ["--mode", "front_wheel"], ["--headless"], ["--viewer"]],
)
def test_play_drive_refuses_scripted_flags(extra, capsys):
    from legged_casters.tools import play

    assert play.main(["--drive", *extra]) != 0
    assert "--drive" in capsys.readouterr().err


def test_play_web_needs_drive(capsys):
    from legged_casters.tools import play

    assert play.main(["--web", "--policy", "zero", "--task", "caster_omni"]) != 0
    assert "--web goes with --drive" in capsys.readouterr().err
