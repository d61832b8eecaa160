"""A single caster on a vertical slider: the test rig for the propulsion relation.

The rig uses `caster.add_caster` with the robot's caster and contact parameters, so
what it validates is what the robot trains on. Only the wheel's rolling resistance
is removed: the paper's relation (section III) assumes pure rolling with no
resistance about the axle, and rolling resistance would add its own force.

    F = N sin(a) cos(a) sin^2(p) / (cos^2(a) sin^2(p) + cos^2(p))
"""

from __future__ import annotations

import dataclasses
import math

import mujoco
import numpy as np

from legged_casters.robot.caster import (
    ModelParams,
    add_caster,
    add_floor,
    apply_contact_options,
)

RIG_LOAD = 50.0  # N, the paper's Fig. 3 load
GRAVITY = 9.81


def propulsion_force(normal: float, alpha: float, phi: float) -> float:
    """The paper's forward force (N) for swivel tilt `alpha` and deflection `phi` (rad)."""
    sa, ca, sp, cp = math.sin(alpha), math.cos(alpha), math.sin(phi), math.cos(phi)
    return normal * sa * ca * sp * sp / (ca * ca * sp * sp + cp * cp)


def build_rig(alpha: float, params: ModelParams | None = None, load: float = RIG_LOAD) -> mujoco.MjModel:
    """Caster with its swivel axis tilted by `alpha` (rad) towards +x, loaded by `load`."""
    params = params or ModelParams()
    caster = dataclasses.replace(params.caster, rolling_resistance_coeff=0.0)
    spec = mujoco.MjSpec()
    spec.modelname = "caster_rig"
    spec.compiler.degree = False
    apply_contact_options(spec, params.contact)
    add_floor(spec, params.contact)
    slider = spec.worldbody.add_body(name="slider", pos=[0, 0, caster.height + 0.01])
    slider.add_joint(name="slide", type=mujoco.mjtJoint.mjJNT_SLIDE, axis=[0, 0, 1])
    slider.mass = load / GRAVITY - caster.total_mass
    slider.inertia = [1e-3, 1e-3, 1e-3]
    slider.ipos = [0, 0, 0]
    slider.explicitinertial = True
    add_caster(slider, "rig", [0, 0, 0], alpha, caster, params.contact)
    spec.add_equality(
        name="hold_swivel", type=mujoco.mjtEq.mjEQ_JOINT, name1="rig_caster_swivel_joint", data=[0.0] * 12
    )
    return spec.compile()


def _wheel_ground_force(model: mujoco.MjModel, data: mujoco.MjData, wheel_geom: int) -> np.ndarray:
    """Sum of the floor's contact forces on the wheel, in the world frame."""
    total = np.zeros(3)
    out = np.zeros(6)
    for i in range(data.ncon):
        con = data.contact[i]
        if wheel_geom not in (con.geom1, con.geom2):
            continue
        mujoco.mj_contactForce(model, data, i, out)
        world = con.frame.reshape(3, 3).T @ out[:3]  # force on geom2 by geom1
        total += world if con.geom2 == wheel_geom else -world
    return total


def measure_force(
    alpha: float,
    phi: float,
    params: ModelParams | None = None,
    settle_time: float = 0.4,
    window: float = 0.004,
) -> tuple[float, float, float]:
    """Release a held caster at deflection `phi` and average the ground force on the wheel.

    The swivel is held at `phi` by a joint equality while the slider settles onto the
    floor, then released; the wheel's contact force (world frame) is averaged over
    `window` seconds after release. Returns (forward F_x, lateral F_y, normal N).
    """
    model = build_rig(alpha, params)
    data = mujoco.MjData(model)
    model.eq_data[0, 0] = phi
    swivel = model.joint("rig_caster_swivel_joint")
    data.qpos[swivel.qposadr[0]] = phi
    wheel = model.geom("rig_wheel").id
    # Start with the wheel's lowest point just touching the floor.
    mujoco.mj_kinematics(model, data)
    rot = data.geom_xmat[wheel].reshape(3, 3)
    lowest = data.geom_xpos[wheel][2] - model.geom_size[wheel][0] * math.sqrt(max(0.0, 1.0 - rot[2, 1] ** 2))
    data.qpos[model.joint("slide").qposadr[0]] -= lowest
    mujoco.mj_forward(model, data)
    for _ in range(int(round(settle_time / model.opt.timestep))):
        mujoco.mj_step(model, data)
    data.eq_active[0] = 0
    steps = max(1, int(round(window / model.opt.timestep)))
    forces = []
    for _ in range(steps):
        mujoco.mj_step(model, data)
        mujoco.mj_forward(model, data)
        forces.append(_wheel_ground_force(model, data, wheel))
    f = np.mean(forces, axis=0)
    return float(f[0]), float(f[1]), float(f[2])
