import mujoco
import pytest

from legged_casters.robot import build


@pytest.fixture(scope="session")
def caster_model() -> mujoco.MjModel:
    return mujoco.MjModel.from_xml_path(str(build.MODEL_FILES["caster"]))


@pytest.fixture(scope="session")
def point_model() -> mujoco.MjModel:
    return mujoco.MjModel.from_xml_path(str(build.MODEL_FILES["point"]))
