import subprocess
from pathlib import Path

import mujoco
import pytest

from legged_casters.robot import build

REPO = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="session")
def caster_model() -> mujoco.MjModel:
    return mujoco.MjModel.from_xml_path(str(build.MODEL_FILES["caster"]))


@pytest.fixture(scope="session")
def point_model() -> mujoco.MjModel:
    return mujoco.MjModel.from_xml_path(str(build.MODEL_FILES["point"]))


@pytest.fixture(scope="session")
def wheel_model() -> mujoco.MjModel:
    return mujoco.MjModel.from_xml_path(str(build.MODEL_FILES["wheel"]))


@pytest.fixture(scope="session")
def models(caster_model, point_model, wheel_model) -> dict[str, mujoco.MjModel]:
    """feet kind -> the committed model."""
    return {"caster": caster_model, "point": point_model, "wheel": wheel_model}


@pytest.fixture
def stop_training():
    """A function that starts a training command line in the repository, reads its output
    until a line contains `at` (e.g. " it 2/200"), calls `stop(proc)` (sends the signal) and
    returns (proc, all its output) once it has exited (60 s at most); `popen` goes to
    subprocess.Popen."""

    def run(cmd: list[str], at: str, stop, **popen) -> tuple[subprocess.Popen, str]:
        proc = subprocess.Popen(cmd, cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, **popen)
        lines = []
        for line in proc.stdout:
            lines.append(line)
            if at in line:
                break
        stop(proc)
        out = "".join(lines) + proc.stdout.read()
        proc.wait(60)
        return proc, out

    return run


REALTIME_TRIES = 3
"""Tries of a wall-clock test (marker `realtime`, or the `realtime` fixture of
tests/test_deploy.py) before it counts as failed."""


def pytest_collection_modifyitems(config, items):
    """Wall-clock tests get REALTIME_TRIES tries (pytest-rerunfailures, each from a fresh
    start: new processes, sessions and tmp_path). They run the bridge and the robot side in
    real time against 30 ms staleness limits and 2 ms physics; on a shared 2-core virtual
    machine one scheduling stall of 30-60 ms (docs/deploy.md, "Timing") fails a try whatever
    the code does. A broken chain fails every try; each failed try is printed in the
    RERUN lines of the summary (-raR)."""
    for item in items:
        if item.get_closest_marker("realtime") or "realtime" in getattr(item, "fixturenames", ()):
            item.add_marker(pytest.mark.flaky(reruns=REALTIME_TRIES - 1, reruns_delay=1))
