"""The generated Go2 models: sizes, names, published data, sensors, keyframe."""

import mujoco
import numpy as np
import pytest

from legged_casters.robot import build, go2
from legged_casters.robot.caster import CasterParams, ContactParams


def test_generator_reproduces_committed_files():
    assert build.stale_files() == [], "regenerate with: python -m legged_casters.robot.build"


def test_xml_matches_tolerates_only_small_numeric_differences():
    assert build.xml_matches('<key qpos="0.3644 1"/>', '<key qpos="0.3645 1"/>')
    assert not build.xml_matches('<key qpos="0.3644 1"/>', '<key qpos="0.3700 1"/>')
    assert not build.xml_matches('<key qpos="0.3644 1"/>', '<key ctrl="0.3644 1"/>')


def test_sizes(caster_model, point_model):
    assert (caster_model.nq, caster_model.nv, caster_model.nu) == (7 + 12 + 8, 6 + 12 + 8, 12)
    assert (point_model.nq, point_model.nv, point_model.nu) == (7 + 12, 6 + 12, 12)


@pytest.mark.parametrize("feet", build.FOOT_KINDS)
def test_actuated_joint_names_order_ranges_and_torque_limits(feet, models):
    model = models[feet]
    assert model.nu == len(go2.action_layout(feet))
    for i, joint in enumerate(go2.ACTUATED_JOINTS):
        act = model.actuator(i)
        assert model.joint(act.trnid[0]).name == joint
        leg, kind = go2.split_joint_name(joint)
        np.testing.assert_allclose(model.joint(joint).range, go2.joint_range(leg, kind))
        np.testing.assert_allclose(act.forcerange, [-go2.TORQUE_LIMIT[kind], go2.TORQUE_LIMIT[kind]])
        assert act.forcelimited
        assert act.gainprm[0] == go2.KP[kind] and act.biasprm[2] == -go2.KD[kind]
    # Published values, spelled out once more so a wrong constant cannot pass silently.
    np.testing.assert_allclose(model.joint("FL_thigh_joint").range, [-1.5708, 3.4907])
    np.testing.assert_allclose(model.joint("RR_thigh_joint").range, [-0.5236, 4.5379])
    np.testing.assert_allclose(model.joint("FR_calf_joint").range, [-2.7227, -0.83776])
    np.testing.assert_allclose(model.actuator("RL_calf").forcerange, [-45.43, 45.43])
    np.testing.assert_allclose(model.actuator("FL_hip").forcerange, [-23.7, 23.7])


def test_passive_caster_joints(caster_model):
    params = CasterParams()
    actuated_dofs = {caster_model.joint(a.trnid[0]).dofadr[0] for a in map(caster_model.actuator, range(12))}
    for name in go2.PASSIVE_JOINTS:
        joint = caster_model.joint(name)
        assert joint.type == mujoco.mjtJoint.mjJNT_HINGE
        assert joint.dofadr[0] not in actuated_dofs
        assert not caster_model.jnt_limited[joint.id]
    for name in go2.SWIVEL_JOINTS:
        dof = caster_model.joint(name).dofadr[0]
        assert caster_model.dof_damping[dof] == pytest.approx(params.swivel_damping)
        assert caster_model.dof_armature[dof] == pytest.approx(params.swivel_armature)
    for name in go2.WHEEL_JOINTS:
        dof = caster_model.joint(name).dofadr[0]
        assert caster_model.dof_frictionloss[dof] == pytest.approx(params.wheel_frictionloss)


def test_bodies_and_sites(caster_model, point_model):
    for model in (caster_model, point_model):
        assert model.body(go2.TRUNK_BODY).id == 1
        assert model.site(go2.IMU_SITE).bodyid[0] == model.body("trunk").id
    for leg in go2.LEGS:
        base = caster_model.body(f"{leg}_caster_base")
        assert caster_model.body(base.parentid[0]).name == f"{leg}_calf"
        assert caster_model.body_jntnum[base.id] == 0  # fixed to the calf end
        fork = caster_model.body(f"{leg}_caster_fork")
        assert caster_model.joint(caster_model.body_jntadr[fork.id]).name == f"{leg}_caster_swivel_joint"
        # The swivel axis is the caster base frame's z axis (the paper's frame F).
        np.testing.assert_allclose(caster_model.joint(f"{leg}_caster_swivel_joint").axis, [0, 0, 1])
        wheel = caster_model.body(f"{leg}_wheel")
        assert wheel.parentid[0] == fork.id


def test_mass(caster_model, point_model):
    point_mass = point_model.body_subtreemass[1]
    lo, hi = go2.GO2_PUBLISHED_MASS_RANGE
    assert lo <= point_mass <= hi
    caster_mass = CasterParams().total_mass
    assert 0.05 <= caster_mass <= 0.3  # a small caster
    assert caster_model.body_subtreemass[1] == pytest.approx(point_mass + 4 * caster_mass)


def test_contact_settings_match_the_validated_ones(caster_model):
    contact = ContactParams()
    assert caster_model.opt.timestep == contact.timestep
    assert caster_model.opt.noslip_iterations == 0
    assert caster_model.opt.impratio == contact.impratio
    for leg in go2.LEGS:
        geom = caster_model.geom(f"{leg}_wheel")
        assert geom.type == mujoco.mjtGeom.mjGEOM_ELLIPSOID
        assert geom.condim == contact.condim
        np.testing.assert_allclose(geom.solref, contact.solref)
        np.testing.assert_allclose(geom.solimp, contact.solimp)


def _sensor(model, data, name):
    s = model.sensor(name)
    return data.sensordata[s.adr[0] : s.adr[0] + s.dim[0]]


def test_sensors_read_the_robot(caster_model):
    model = caster_model
    data = mujoco.MjData(model)
    mujoco.mj_resetDataKeyframe(model, data, 0)
    rng = np.random.default_rng(0)
    data.qvel[:] = rng.normal(0, 0.3, model.nv)
    mujoco.mj_forward(model, data)
    for joint in go2.ACTUATED_JOINTS + go2.PASSIVE_JOINTS:
        j = model.joint(joint)
        assert _sensor(model, data, f"{joint}_pos")[0] == pytest.approx(data.qpos[j.qposadr[0]])
        assert _sensor(model, data, f"{joint}_vel")[0] == pytest.approx(data.qvel[j.dofadr[0]])
    for joint in go2.ACTUATED_JOINTS:
        assert _sensor(model, data, f"{joint}_torque")[0] == pytest.approx(
            data.actuator_force[model.actuator(joint.replace("_joint", "")).id]
        )
    np.testing.assert_allclose(_sensor(model, data, "imu_quat"), data.qpos[3:7], atol=1e-9)
    np.testing.assert_allclose(_sensor(model, data, "imu_gyro"), data.qvel[3:6], atol=1e-9)  # site not rotated
    site = model.site("imu").id
    v = np.zeros(6)
    mujoco.mj_objectVelocity(model, data, mujoco.mjtObj.mjOBJ_SITE, site, v, 0)
    np.testing.assert_allclose(_sensor(model, data, "trunk_linvel_world"), v[3:], atol=1e-9)
    for leg in go2.LEGS:
        zaxis = data.site_xmat[model.site(f"{leg}_caster_base").id].reshape(3, 3)[:, 2]
        np.testing.assert_allclose(_sensor(model, data, f"{leg}_caster_zaxis"), zaxis, atol=1e-12)


def test_keyframe_stands_on_the_wheels_only(caster_model, point_model):
    for model, feet in ((caster_model, "wheel"), (point_model, "foot")):
        data = mujoco.MjData(model)
        mujoco.mj_resetDataKeyframe(model, data, model.key(build.STAND_KEY).id)
        for _ in range(50):
            mujoco.mj_step(model, data)
        weight = model.body_subtreemass[1] * 9.81
        loads = []
        for leg in go2.LEGS:
            found, *force = _sensor(model, data, f"{leg}_{feet}_contact")
            assert found >= 1
            loads.append(np.linalg.norm(force))
            assert _sensor(model, data, f"{leg}_calf_contact")[0] == 0
        assert sum(loads) == pytest.approx(weight, rel=0.05)
        assert _sensor(model, data, "trunk_contact")[0] == 0
        np.testing.assert_allclose(data.ctrl, go2.default_joint_positions())
