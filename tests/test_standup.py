"""The bridge's folding stand-up on the simulated caster robot: from the floor, in process
and through the process chain (scripts/standup_check.py measures the same at scale)."""

import importlib.util
import sys
from pathlib import Path

import numpy as np
import pytest

from legged_casters.deploy import protocol as P
from legged_casters.deploy import unitree
from legged_casters.deploy.bridge import SHIPPED_POLICY
from legged_casters.deploy.policy import PolicyRunner, load_meta

ROOT = Path(__file__).resolve().parents[1]


def _load_check():
    spec = importlib.util.spec_from_file_location("standup_check", ROOT / "scripts" / "standup_check.py")
    mod = importlib.util.module_from_spec(spec)
    sys.modules["standup_check"] = mod
    spec.loader.exec_module(mod)
    return mod


@pytest.fixture(scope="module")
def check():
    return _load_check()


@pytest.fixture(scope="module")
def shipped():
    meta = load_meta(SHIPPED_POLICY)
    return meta, PolicyRunner(meta, "onnx")


def test_a_collapsed_robot_stands_up_with_the_fold_and_not_with_the_ramp(check, shipped):
    """A robot that collapsed under damping lies on its belly (trunk about 6 cm up): the fold
    stand-up stands it (height within 3 cm, tilt under 10 deg) within 4 s; the linear ramp
    leaves it sitting on its rear casters (docs/deploy.md)."""
    meta, runner = shipped
    result = {}
    for standup in ("fold", "linear"):
        chain = check.Chain(meta, runner, standup)
        chain.run(3.0)
        assert chain.robot.data.qpos[2] < 0.12  # lying
        chain.attach_bridge()
        result[standup] = chain.time_to_stand(4.0)
        assert chain.bridge.fault is not P.Fault.INTERNAL_ERROR
    assert result["fold"] is not None and result["fold"] < 3.5
    assert result["linear"] is None


def test_the_bridge_damps_a_fallen_robot_and_a_reset_runs_the_stand_up_again(check, shipped):
    meta, runner = shipped
    chain = check.Chain(meta, runner, "fold")
    chain.run(1.0)
    chain.attach_bridge()
    assert chain.time_to_stand(4.0) is not None
    chain.run(1.0, push=np.array([0.0, 400.0, 0.0]), push_s=0.3)  # a hard shove sideways
    chain.run(1.0)
    assert chain.bridge.state is P.BridgeState.DAMPING and chain.bridge.fault is P.Fault.FALLEN
    n = len(chain.bridge.transitions)
    chain.operate(reset=True)
    chain.run(0.5)
    states = [s for _, s, _ in chain.bridge.transitions[n:]]
    assert states[:2] == [P.BridgeState.WAITING, P.BridgeState.STANDUP]


def _on_its_back(check, meta, runner, **bridge):
    """A robot dropped upside down, damped 2 s (it lies on its back), then the bridge starts."""
    import mujoco

    from legged_casters.robot import build

    chain = check.Chain(meta, runner, "fold")
    m, d = chain.robot.model, chain.robot.data
    d.qpos[:] = m.key_qpos[mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_KEY, build.STAND_KEY)]
    d.qpos[2], d.qpos[3:7] = 0.35, [0.0, 1.0, 0.0, 0.0]  # 180 deg about the trunk's x axis
    d.qvel[:] = 0.0
    mujoco.mj_forward(m, d)
    chain.run(2.0)
    assert chain.tilt() > 150.0
    chain.attach_bridge(**bridge)
    return chain


def test_a_wheel_robot_on_its_back_is_righted_by_the_same_keyframes(check):
    """The keyframes were searched on the caster robot; the driving-wheel Go2's legs are the
    same, and the bridge rights it and hands it to its policy the same way."""
    meta = load_meta(ROOT / "resources" / "policies" / "go2_wheel_flat")
    chain = _on_its_back(check, meta, PolicyRunner(meta, "onnx"))
    for _ in range(120):
        chain.run(0.1)
        if chain.bridge.state is not P.BridgeState.STANDUP:
            break
    chain.run(1.0)
    assert chain.bridge.state is P.BridgeState.RUNNING and chain.upright() and len(chain.bridge.notes) == 1


def test_a_robot_on_its_back_is_righted_stands_up_and_skates(check, shipped):
    """The righting keyframes roll it onto its belly, the fold stands it up, the policy
    skates; without righting the fold cannot, and the bridge damps it as fallen."""
    meta, runner = shipped
    chain = _on_its_back(check, meta, runner)
    b = chain.bridge
    for _ in range(120):  # up to 12 s
        chain.run(0.1)
        if b.state is not P.BridgeState.STANDUP:
            break
    assert b.state is P.BridgeState.RUNNING and b.fault is P.Fault.NONE
    assert b.notes and b.notes[0].startswith("STANDUP: righting, try 1 of 3")
    chain.run(1.0)
    chain.operate(0.5)
    x0 = chain.robot.data.qpos[:2].copy()
    chain.run(3.0)
    assert chain.upright() and np.linalg.norm(chain.robot.data.qpos[:2] - x0) > 0.8

    chain = _on_its_back(check, meta, runner, righting=False)
    chain.run(chain.bridge.folding.duration + 1.0)
    assert chain.bridge.fault is P.Fault.FALLEN and not chain.bridge.notes


@pytest.mark.realtime
@pytest.mark.parametrize("robot", ["sim", "go2"])
def test_the_process_chain_stands_up_from_lying_and_skates(check, robot, request):
    """sim_robot, or fake_go2 + go2_adapter over loopback DDS (started damped: it lies) ->
    bridge (fold stand-up) -> operator vx 0.5."""
    if robot == "go2":
        try:
            unitree.load_sdk()
        except unitree.SdkUnavailable as err:
            pytest.skip(f"Unitree SDK not installed: {err}")
    args = check.build_parser().parse_args(["--trials", "0", "--falls", "0", "--robot", robot])

    # a new port and namespace on each try (conftest.py: REALTIME_TRIES)
    r = check.loopback(args, getattr(request.node, "execution_count", 1))
    assert r is not None, "the bridge never ran"
    print(r)
    assert r["lying_z"] < 0.12 and r["stand_s"] < 4.0
    assert r["fault"] == "NONE" and r["state"] == "RUNNING"
    assert r["along_m"] > 2.0  # 10 s at 0.5 m/s
