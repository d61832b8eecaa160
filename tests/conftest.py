import mujoco
import pytest

from legged_casters.robot import build


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
