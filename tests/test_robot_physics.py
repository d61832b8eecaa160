"""The whole caster robot: standing, coasting with rolling resistance, no side slip,
and the legs' authority over the swivel-axis tilt."""

import dataclasses

import mujoco
import numpy as np
import pytest

from legged_casters.robot import build, go2
from legged_casters.robot.caster import CasterParams, ModelParams

GRAVITY = 9.81


def _tilt_deg(data: mujoco.MjData) -> float:
    up = data.xmat[1].reshape(3, 3)[:, 2]
    return float(np.degrees(np.arccos(np.clip(up[2], -1, 1))))


def _stand(model, seconds):
    data = mujoco.MjData(model)
    mujoco.mj_resetDataKeyframe(model, data, model.key(build.STAND_KEY).id)
    start = data.qpos[:3].copy()
    drift = height = tilt = 0.0
    touched = set()
    allowed = {model.geom(f"{leg}_wheel").id for leg in go2.LEGS} | {model.geom("floor").id}
    for _ in range(int(seconds / model.opt.timestep)):
        mujoco.mj_step(model, data)
        drift = max(drift, float(np.linalg.norm(data.qpos[:2] - start[:2])))
        height = max(height, abs(float(data.qpos[2] - start[2])))
        tilt = max(tilt, _tilt_deg(data))
        for i in range(data.ncon):
            touched |= {data.contact[i].geom1, data.contact[i].geom2} - allowed
    return drift, height, tilt, touched


def test_stands_still_for_20_seconds(caster_model):
    # Measured: 2.9 cm drift, 0.9 mm height change, < 0.5 deg tilt.
    drift, height, tilt, touched = _stand(caster_model, 20.0)
    assert drift < 0.05 and height < 0.01 and tilt < 3.0, (drift, height, tilt)
    assert not touched


@pytest.mark.parametrize("damping", (0.01, 0.1))
def test_stands_at_the_randomised_swivel_damping_bounds(damping):
    params = ModelParams(caster=CasterParams(swivel_damping=damping))
    drift, height, tilt, touched = _stand(build.load_model("caster", params), 10.0)
    assert drift < 0.05 and height < 0.01 and tilt < 3.0, (drift, height, tilt)
    assert not touched


def _coast(model, v0, seconds):
    data = mujoco.MjData(model)
    mujoco.mj_resetDataKeyframe(model, data, model.key(build.STAND_KEY).id)
    for _ in range(100):
        mujoco.mj_step(model, data)
    data.qvel[0] = v0
    speeds = []
    for _ in range(int(seconds / model.opt.timestep)):
        mujoco.mj_step(model, data)
        speeds.append(float(data.qvel[0]))
    return data, np.array(speeds)


def test_pushed_robot_rolls_and_slows_through_rolling_resistance(caster_model):
    params = CasterParams()
    dt = caster_model.opt.timestep
    data, speeds = _coast(caster_model, 1.0, 7.0)
    # Coulomb rolling resistance decelerates at about c_rr * g.
    expected = params.rolling_resistance_coeff * GRAVITY
    decel = (speeds[int(0.5 / dt)] - speeds[int(2.5 / dt)]) / 2.0
    assert decel == pytest.approx(expected, rel=0.15)
    assert abs(speeds[-1]) < 0.02  # it has come to rest
    assert data.qpos[0] == pytest.approx(1.0**2 / (2 * expected), rel=0.15)
    assert _tilt_deg(data) < 3.0
    # Without rolling resistance it would coast on: the resistance is what stops it.
    frictionless = build.load_model(
        "caster", ModelParams(caster=dataclasses.replace(params, rolling_resistance_coeff=0))
    )
    _, free_speeds = _coast(frictionless, 1.0, 3.0)
    assert free_speeds[-1] > 0.95


def test_rolling_wheels_do_not_slip_sideways(caster_model):
    model = caster_model
    data = mujoco.MjData(model)
    mujoco.mj_resetDataKeyframe(model, data, 0)
    for _ in range(100):
        mujoco.mj_step(model, data)
    data.qvel[0] = 1.0
    vel = np.zeros(6)
    worst = 0.0
    wheels = {model.geom(f"{leg}_wheel").id: model.body(f"{leg}_wheel").id for leg in go2.LEGS}
    for step in range(1500):
        mujoco.mj_step(model, data)
        if step < 50:
            continue
        for i in range(data.ncon):
            con = data.contact[i]
            geom = con.geom1 if con.geom1 in wheels else con.geom2
            if geom not in wheels:
                continue
            body = wheels[geom]
            mujoco.mj_objectVelocity(model, data, mujoco.mjtObj.mjOBJ_BODY, body, vel, 0)
            at_contact = vel[3:] + np.cross(vel[:3], con.pos - data.xpos[body])
            axle = data.xmat[body].reshape(3, 3)[:, 1].copy()
            axle[2] = 0.0
            worst = max(worst, abs(float(at_contact @ axle / np.linalg.norm(axle))))
    # Measured: 1.3 mm/s peak side slip while rolling at 1 m/s.
    assert worst < 0.01


@pytest.mark.parametrize("leg", go2.LEGS)
def test_legs_tilt_the_swivel_axis_20_degrees_both_ways_while_standing(caster_model, leg):
    """With the trunk at its standing pose, some in-range thigh/calf angles keep the
    wheel on the floor (within 2 mm) with the swivel axis tilted >= 20 deg forward,
    and others with it tilted >= 20 deg backward."""
    model = caster_model
    data = mujoco.MjData(model)
    mujoco.mj_resetDataKeyframe(model, data, 0)
    adr = [model.joint(f"{leg}_{k}_joint").qposadr[0] for k in ("thigh", "calf")]
    site, wheel = model.site(f"{leg}_caster_base").id, model.geom(f"{leg}_wheel").id
    sx = go2.leg_signs(leg)[0]
    tilts = []
    for thigh in np.linspace(*go2.joint_range(leg, "thigh"), 240):
        for calf in np.linspace(*go2.CALF_RANGE, 160):
            data.qpos[adr] = thigh, calf
            mujoco.mj_kinematics(model, data)
            rot = data.geom_xmat[wheel].reshape(3, 3)
            lowest = data.geom_xpos[wheel][2] - model.geom_size[wheel][0] * np.sqrt(1 - rot[2, 1] ** 2)
            if abs(lowest) < 0.002:
                z = data.site_xmat[site].reshape(3, 3)[:, 2]
                tilts.append(np.degrees(np.arctan2(z[0], z[2])))
    assert sx != 0 and tilts
    assert max(tilts) >= 20.0 and min(tilts) <= -20.0, (min(tilts), max(tilts))


@pytest.mark.parametrize("feet", build.FOOT_KINDS)
def test_survives_perturbed_starts_and_random_targets(feet, models):
    """Contact settings that are stiff enough for the caster rig can fling the robot
    or blow up under abuse (docs/robot.md); these must not. (The wheel
    robot's wheels get random velocity targets too.)"""
    model = models[feet]
    data = mujoco.MjData(model)
    layout = go2.action_layout(feet)
    nominal = np.array(layout.default)
    spread = np.where(layout.position_mask, 0.3, 6.0)  # rad, or rad/s for wheels
    adr = [model.joint(j).qposadr[0] for j in go2.ACTUATED_JOINTS]
    every = int(round(0.02 / model.opt.timestep))
    for seed in range(10):
        rng = np.random.default_rng(seed)
        mujoco.mj_resetDataKeyframe(model, data, 0)
        data.qpos[adr] += rng.uniform(-0.2, 0.2, 12)
        mujoco.mj_kinematics(model, data)
        data.qpos[2] -= build.ground_clearance(model, data, feet)
        data.qvel[:6] = rng.uniform(-0.3, 0.3, 6)
        for i in range(int(1.5 / model.opt.timestep)):
            if i % every == 0:
                data.ctrl[:] = nominal + rng.normal(0.0, 1.0, model.nu) * spread
            mujoco.mj_step(model, data)
            assert data.warning[mujoco.mjtWarning.mjWARN_BADQACC].number == 0, f"seed {seed}: simulation blew up"
            assert data.qpos[2] < 0.6, f"seed {seed}: trunk flung to {data.qpos[2]:.2f} m at t={data.time:.2f}"


def test_open_loop_wiggle_skates_along_the_swivel_tilt(caster_model):
    """The paper's mechanism on the whole robot, no learning: the same hip swing
    skates forward with the swivel axes tilted forward and backward with them tilted
    backward. Measured (10 s): +24 deg -> +1.38 m/s, -24 deg -> -1.17 m/s, COT_mech
    0.07-0.08 (the paper's caster robot: 0.0705)."""
    from legged_casters.robot.skate import BACKWARD, FORWARD, skate

    fwd = skate(caster_model, FORWARD, duration=5.0)
    back = skate(caster_model, BACKWARD, duration=5.0)
    assert fwd["upright"] and back["upright"]
    assert fwd["tilt_deg"] > 15 and back["tilt_deg"] < -15
    assert fwd["speed"] > 0.5 and back["speed"] < -0.5, (fwd, back)
    assert abs(fwd["lateral_drift"]) < 0.1 and abs(back["lateral_drift"]) < 0.1
    assert fwd["cot"] < 0.3 and back["cot"] < 0.3
