"""Generate the Go2 MJCF models (caster feet, point feet, driving wheels) from one source.

    python -m legged_casters.robot.build            # rewrite the committed XML files
    python -m legged_casters.robot.build --check    # fail if they are out of date

All robots share the trunk and legs built here from `go2.py`; only the foot
differs: a passive caster (`caster.add_caster`), the Go2's rubber sphere, or an
actuated driving wheel (`_add_drive_wheel`). The actuators follow
`go2.action_layout(feet)`.
"""

from __future__ import annotations

import argparse
import math
import re
import sys
from pathlib import Path

import mujoco
import numpy as np

from legged_casters.robot import go2
from legged_casters.robot.caster import (
    ModelParams,
    add_caster,
    add_floor,
    apply_contact_options,
    box_inertia,
    cylinder_inertia,
    set_contact,
)

REPO_ROOT = Path(__file__).resolve().parents[2]
MODEL_DIR = REPO_ROOT / "resources" / "robots" / "go2_caster"
FOOT_KINDS = go2.FOOT_KINDS
MODEL_NAMES = dict(zip(FOOT_KINDS, ("go2_caster", "go2_point_foot", "go2_wheel"), strict=True))
MODEL_FILES = {feet: MODEL_DIR / f"{name}.xml" for feet, name in MODEL_NAMES.items()}

STAND_KEY = "stand"
_CONTACT_DATA = 1 | 2  # found + force
_CONTACT_REDUCE_NETFORCE = 3


def _quat_y(angle: float) -> list[float]:
    return [math.cos(angle / 2), 0.0, math.sin(angle / 2), 0.0]


def _add_visual_assets(spec: mujoco.MjSpec) -> None:
    spec.add_texture(
        name="grid",
        type=mujoco.mjtTexture.mjTEXTURE_2D,
        builtin=mujoco.mjtBuiltin.mjBUILTIN_CHECKER,
        rgb1=[0.2, 0.3, 0.4],
        rgb2=[0.1, 0.15, 0.2],
        width=512,
        height=512,
        mark=mujoco.mjtMark.mjMARK_EDGE,
        markrgb=[0.6, 0.6, 0.6],
    )
    mat = spec.add_material(name="grid", texrepeat=[1, 1], texuniform=True, reflectance=0.1)
    mat.textures[mujoco.mjtTextureRole.mjTEXROLE_RGB] = "grid"
    spec.add_texture(
        name="skybox",
        type=mujoco.mjtTexture.mjTEXTURE_SKYBOX,
        builtin=mujoco.mjtBuiltin.mjBUILTIN_GRADIENT,
        rgb1=[0.3, 0.5, 0.7],
        rgb2=[0, 0, 0],
        width=512,
        height=3072,
    )
    spec.worldbody.add_light(
        name="sun", pos=[0, 0, 3], dir=[0, 0, -1], type=mujoco.mjtLightType.mjLIGHT_DIRECTIONAL, castshadow=1
    )
    spec.visual.global_.offwidth = 1280
    spec.visual.global_.offheight = 720


def _add_contact_sensor(spec: mujoco.MjSpec, name: str, body: str) -> None:
    sensor = spec.add_sensor(name=name, type=mujoco.mjtSensor.mjSENS_CONTACT, objtype=mujoco.mjtObj.mjOBJ_BODY)
    sensor.objname = body
    sensor.intprm[0] = _CONTACT_DATA
    sensor.intprm[1] = _CONTACT_REDUCE_NETFORCE
    sensor.intprm[2] = 1


def _add_sensor(spec: mujoco.MjSpec, name: str, stype, objtype, objname: str) -> None:
    sensor = spec.add_sensor(name=name, type=stype, objtype=objtype)
    sensor.objname = objname


def build_spec(feet: str = "caster", params: ModelParams | None = None) -> mujoco.MjSpec:
    """Build the Go2 with `feet` = 'caster', 'point' or 'wheel' as an MjSpec (not compiled)."""
    if feet not in FOOT_KINDS:
        raise ValueError(f"feet must be one of {FOOT_KINDS}, got {feet!r}")
    params = params or ModelParams()
    caster, contact = params.caster, params.contact
    spec = mujoco.MjSpec()
    spec.modelname = MODEL_NAMES[feet]
    spec.compiler.degree = False
    spec.compiler.autolimits = True
    apply_contact_options(spec, contact)
    _add_visual_assets(spec)
    add_floor(spec, contact, material="grid")

    trunk = spec.worldbody.add_body(name=go2.TRUNK_BODY, pos=[0, 0, 0.4])
    trunk.add_freejoint(name=go2.ROOT_JOINT)
    trunk.mass = go2.TRUNK_MASS
    trunk.inertia = box_inertia(go2.TRUNK_MASS, go2.TRUNK_SIZE)
    trunk.ipos = [0.0213, 0.0, -0.0051]  # Go2 trunk CoM is slightly forward of the origin
    trunk.explicitinertial = True
    tg = trunk.add_geom(name="trunk", type=mujoco.mjtGeom.mjGEOM_BOX, size=[s / 2 for s in go2.TRUNK_SIZE])
    tg.rgba = [0.85, 0.85, 0.88, 1]
    set_contact(tg, contact)
    head = trunk.add_geom(name="head", type=mujoco.mjtGeom.mjGEOM_BOX, size=[0.04, 0.05, 0.04], pos=[0.22, 0, 0.01])
    head.rgba = [0.2, 0.2, 0.22, 1]
    set_contact(head, contact)
    trunk.add_site(name=go2.IMU_SITE, pos=[-0.02557, 0, 0.04232], size=[0.01, 0, 0])
    trunk.add_camera(
        name="track", mode=mujoco.mjtCamLight.mjCAMLIGHT_TRACKCOM, pos=[0, -2.2, 0.8], xyaxes=[1, 0, 0, 0, 0.34, 1]
    )

    for leg in go2.LEGS:
        sx, sy = go2.leg_signs(leg)
        hip = trunk.add_body(name=f"{leg}_hip", pos=[sx * go2.HIP_OFFSET[0], sy * go2.HIP_OFFSET[1], 0])
        hip.add_joint(
            name=f"{leg}_hip_joint",
            axis=[1, 0, 0],
            range=list(go2.joint_range(leg, "hip")),
            armature=go2.MOTOR_ARMATURE,
        )
        hip.mass = go2.HIP_MASS
        hip.ipos = [-sx * 0.0054, sy * 0.00194, 0]
        hip.inertia = cylinder_inertia(go2.HIP_MASS, 0.046, 0.04, axis=1)
        hip.explicitinertial = True
        hg = hip.add_geom(
            name=f"{leg}_hip",
            type=mujoco.mjtGeom.mjGEOM_CYLINDER,
            size=[0.046, 0.02, 0],
            pos=[0, sy * 0.055, 0],
            quat=[math.cos(math.pi / 4), math.sin(math.pi / 4), 0, 0],
        )
        hg.rgba = [0.2, 0.2, 0.22, 1]
        set_contact(hg, contact)

        thigh = hip.add_body(name=f"{leg}_thigh", pos=[0, sy * go2.THIGH_OFFSET[1], 0])
        thigh.add_joint(
            name=f"{leg}_thigh_joint",
            axis=[0, 1, 0],
            range=list(go2.joint_range(leg, "thigh")),
            armature=go2.MOTOR_ARMATURE,
        )
        thigh.mass = go2.THIGH_MASS
        thigh.ipos = [-0.00374, -sy * 0.0223, -0.0327]
        thigh.inertia = box_inertia(go2.THIGH_MASS, (0.034, 0.034, go2.THIGH_LENGTH))
        thigh.explicitinertial = True
        tgeom = thigh.add_geom(
            name=f"{leg}_thigh",
            type=mujoco.mjtGeom.mjGEOM_BOX,
            size=[0.0245, 0.017, go2.THIGH_LENGTH / 2],
            pos=[0, 0, -go2.THIGH_LENGTH / 2],
        )
        tgeom.rgba = [0.85, 0.85, 0.88, 1]
        set_contact(tgeom, contact)

        calf = thigh.add_body(name=f"{leg}_calf", pos=[0, 0, -go2.THIGH_LENGTH])
        calf.add_joint(
            name=f"{leg}_calf_joint",
            axis=[0, 1, 0],
            range=list(go2.joint_range(leg, "calf")),
            armature=go2.MOTOR_ARMATURE,
        )
        calf.mass = go2.CALF_MASS
        calf.ipos = [0.00548, 0, -0.0975]
        calf.inertia = cylinder_inertia(go2.CALF_MASS, 0.012, go2.CALF_LENGTH, axis=2)
        calf.explicitinertial = True
        cg = calf.add_geom(
            name=f"{leg}_calf",
            type=mujoco.mjtGeom.mjGEOM_CAPSULE,
            size=[0.012, 0, 0],
            fromto=[0, 0, -0.01, 0, 0, -go2.CALF_LENGTH + 0.012],
        )
        cg.rgba = [0.2, 0.2, 0.22, 1]
        set_contact(cg, contact)

        end = [0, 0, -go2.CALF_LENGTH]
        if feet == "caster":
            add_caster(calf, leg, end, math.radians(caster.mount_angle), caster, contact)
        elif feet == "wheel":
            _add_drive_wheel(calf, leg, end, caster.rolling_resistance_coeff, contact)
        else:
            foot = calf.add_body(name=f"{leg}_foot", pos=end)
            fg = foot.add_geom(name=f"{leg}_foot", type=mujoco.mjtGeom.mjGEOM_SPHERE, size=[go2.FOOT_RADIUS, 0, 0])
            fg.rgba = [0.1, 0.1, 0.1, 1]
            set_contact(fg, contact)
            fg.mass = 0.0  # the foot's mass is part of the calf's published mass
            foot.add_site(name=f"{leg}_foot", size=[0.005, 0, 0])

    layout = go2.action_layout(feet)
    for i, joint in enumerate(layout.joints):
        act = spec.add_actuator(name=actuator_name(joint), target=joint, trntype=mujoco.mjtTrn.mjTRN_JOINT)
        if layout.control[i] == go2.CONTROL_POSITION:
            act.set_to_position(kp=layout.kp[i], kv=layout.kd[i])
        else:
            act.set_to_velocity(kv=layout.kd[i])
        act.ctrlrange = list(layout.ranges[i])
        act.ctrllimited = mujoco.mjtLimited.mjLIMITED_TRUE
        act.forcerange = [-layout.torque_limits[i], layout.torque_limits[i]]
        act.forcelimited = mujoco.mjtLimited.mjLIMITED_TRUE

    _add_sensors(spec, feet)
    _add_stand_key(spec, feet)
    return spec


def actuator_name(joint: str) -> str:
    """'FL_hip_joint' -> 'FL_hip': the actuator driving a joint."""
    return joint.replace("_joint", "")


def _add_drive_wheel(calf: mujoco.MjsBody, leg: str, end: list[float], c_rr: float, contact) -> None:
    """An actuated wheel at the calf end, axle along the calf's y axis, its mid-plane
    `DRIVE_WHEEL_OFFSET` outboard. Body and geom {leg}_wheel, joint {leg}_wheel_joint."""
    _, sy = go2.leg_signs(leg)
    r, w, m = go2.DRIVE_WHEEL_RADIUS, go2.DRIVE_WHEEL_WIDTH, go2.DRIVE_WHEEL_MASS
    wheel = calf.add_body(name=f"{leg}_wheel", pos=[end[0], sy * go2.DRIVE_WHEEL_OFFSET, end[2]])
    # Rolling resistance modelled as on the casters: Coulomb friction on the axle,
    # tau = c_rr * N * R, with N the robot's weight / 4.
    load = (_robot_mass("wheel")) * 9.81 / 4
    wheel.add_joint(
        name=f"{leg}_wheel_joint",
        type=mujoco.mjtJoint.mjJNT_HINGE,
        axis=[0, 1, 0],
        armature=go2.MOTOR_ARMATURE,
        frictionloss=c_rr * load * r,
    )
    wheel.mass = m
    wheel.ipos = [0, 0, 0]
    wheel.inertia = cylinder_inertia(m, r, w, axis=1)
    wheel.explicitinertial = True
    tire = wheel.add_geom(
        name=f"{leg}_wheel",
        type=mujoco.mjtGeom.mjGEOM_CYLINDER,
        size=[r, w / 2, 0],
        quat=[math.cos(math.pi / 4), math.sin(math.pi / 4), 0, 0],
    )
    tire.rgba = [0.15, 0.15, 0.15, 1]
    tire.mass = 0.0
    set_contact(tire, contact)
    wheel.add_geom(  # a rim marker makes rotation visible in videos
        type=mujoco.mjtGeom.mjGEOM_BOX,
        size=[0.008, w / 2 + 0.001, 0.008],
        pos=[r * 0.75, 0, 0],
        contype=0,
        conaffinity=0,
        group=1,
        rgba=[0.9, 0.6, 0.1, 1],
        mass=0.0,
    )
    wheel.add_site(name=f"{leg}_wheel", size=[0.005, 0, 0])


def _robot_mass(feet: str) -> float:
    legs = 4 * (go2.HIP_MASS + go2.THIGH_MASS + go2.CALF_MASS)
    extra = 4 * go2.DRIVE_WHEEL_MASS if feet == "wheel" else 0.0
    return go2.TRUNK_MASS + legs + extra


def _add_sensors(spec: mujoco.MjSpec, feet: str) -> None:
    S, O = mujoco.mjtSensor, mujoco.mjtObj
    _add_sensor(spec, "imu_gyro", S.mjSENS_GYRO, O.mjOBJ_SITE, go2.IMU_SITE)
    _add_sensor(spec, "imu_acc", S.mjSENS_ACCELEROMETER, O.mjOBJ_SITE, go2.IMU_SITE)
    _add_sensor(spec, "imu_quat", S.mjSENS_FRAMEQUAT, O.mjOBJ_SITE, go2.IMU_SITE)
    _add_sensor(spec, "trunk_pos", S.mjSENS_FRAMEPOS, O.mjOBJ_SITE, go2.IMU_SITE)
    _add_sensor(spec, "trunk_linvel_world", S.mjSENS_FRAMELINVEL, O.mjOBJ_SITE, go2.IMU_SITE)
    _add_sensor(spec, "trunk_angvel_world", S.mjSENS_FRAMEANGVEL, O.mjOBJ_SITE, go2.IMU_SITE)
    actuated = go2.action_layout(feet).joints
    joints = list(actuated) + (list(go2.PASSIVE_JOINTS) if feet == "caster" else [])
    for joint in joints:
        _add_sensor(spec, f"{joint}_pos", S.mjSENS_JOINTPOS, O.mjOBJ_JOINT, joint)
    for joint in joints:
        _add_sensor(spec, f"{joint}_vel", S.mjSENS_JOINTVEL, O.mjOBJ_JOINT, joint)
    for joint in actuated:
        _add_sensor(spec, f"{joint}_torque", S.mjSENS_ACTUATORFRC, O.mjOBJ_ACTUATOR, actuator_name(joint))
    if feet == "caster":
        for leg in go2.LEGS:
            _add_sensor(spec, f"{leg}_caster_zaxis", S.mjSENS_FRAMEZAXIS, O.mjOBJ_SITE, f"{leg}_caster_base")
    _add_contact_sensor(spec, "trunk_contact", go2.TRUNK_BODY)
    for leg in go2.LEGS:
        _add_contact_sensor(spec, f"{leg}_thigh_contact", f"{leg}_thigh")
        _add_contact_sensor(spec, f"{leg}_calf_contact", f"{leg}_calf")
        if feet == "caster":
            _add_contact_sensor(spec, f"{leg}_caster_base_contact", f"{leg}_caster_base")
            _add_contact_sensor(spec, f"{leg}_caster_fork_contact", f"{leg}_caster_fork")
            _add_contact_sensor(spec, f"{leg}_wheel_contact", f"{leg}_wheel")
        elif feet == "wheel":
            _add_contact_sensor(spec, f"{leg}_wheel_contact", f"{leg}_wheel")
        else:
            _add_contact_sensor(spec, f"{leg}_foot_contact", f"{leg}_foot")


def ground_clearance(model: mujoco.MjModel, data: mujoco.MjData, feet: str) -> float:
    """Height of the lowest ground-touching point of the feet above z = 0."""
    lowest = np.inf
    for leg in go2.LEGS:
        if feet == "caster":
            gid = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, f"{leg}_wheel")
            # Lowest point of the wheel disk: centre minus R times the in-plane
            # direction closest to -z.
            rot = data.geom_xmat[gid].reshape(3, 3)
            axle = rot[:, 1]
            down = np.array([0.0, 0.0, -1.0]) - axle * (-axle[2])
            down /= np.linalg.norm(down)
            low = data.geom_xpos[gid][2] + model.geom_size[gid][0] * down[2]
        elif feet == "wheel":
            # A cylinder (axle = its z axis): the lowest rim point of its lower face.
            gid = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, f"{leg}_wheel")
            axle = data.geom_xmat[gid].reshape(3, 3)[:, 2]
            radial = np.sqrt(max(0.0, 1.0 - axle[2] ** 2))
            r, half = model.geom_size[gid][0], model.geom_size[gid][1]
            low = data.geom_xpos[gid][2] - r * radial - half * abs(axle[2])
        else:
            gid = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, f"{leg}_foot")
            low = data.geom_xpos[gid][2] - model.geom_size[gid][0]
        lowest = min(lowest, low)
    return float(lowest)


def _settle(model: mujoco.MjModel, data: mujoco.MjData, feet: str, seconds: float = 3.0) -> None:
    """Let the robot sag onto its PD-held legs with the trunk's horizontal motion, its
    rotation and the swivels frozen, so the keyframe is a static equilibrium."""
    swivels, swivel_q = [], []
    if feet == "caster":
        swivels = [model.jnt_dofadr[model.joint(j).id] for j in go2.SWIVEL_JOINTS]
        swivel_q = [model.jnt_qposadr[model.joint(j).id] for j in go2.SWIVEL_JOINTS]
    for _ in range(int(seconds / model.opt.timestep)):
        mujoco.mj_step(model, data)
        data.qvel[[0, 1, 3, 4, 5]] = 0.0
        data.qpos[3:7] = [1.0, 0.0, 0.0, 0.0]
        data.qvel[swivels] = 0.0
        data.qpos[swivel_q] = 0.0


def _add_stand_key(spec: mujoco.MjSpec, feet: str) -> None:
    """Standing keyframe: nominal joint targets, the robot settled on the floor."""
    model = spec.compile()
    data = mujoco.MjData(model)
    qpos = model.qpos0.copy()
    layout = go2.action_layout(feet)
    for joint, value in zip(layout.joints, layout.default, strict=True):
        qpos[model.jnt_qposadr[model.joint(joint).id]] = value
    qpos[2] = 0.0
    data.qpos[:] = qpos
    mujoco.mj_kinematics(model, data)
    data.qpos[2] = -ground_clearance(model, data, feet)
    data.ctrl[:] = layout.default
    _settle(model, data, feet)
    qpos = data.qpos.copy()
    qpos[0:2] = 0.0
    wheels = {"caster": go2.WHEEL_JOINTS, "wheel": go2.DRIVE_WHEEL_JOINTS}.get(feet, ())
    # Wheel rotation is irrelevant to the stance; start at zero.
    qpos[[model.jnt_qposadr[model.joint(j).id] for j in wheels]] = 0.0
    # Rounded so that the file does not depend on the last bits of the platform's maths.
    spec.add_key(name=STAND_KEY, qpos=np.round(qpos, 4).tolist(), ctrl=list(layout.default))


_NUMBER = re.compile(r"-?\d+\.?\d*(?:e[-+]?\d+)?")


def xml_matches(a: str, b: str, tol: float = 2e-4) -> bool:
    """Equal XML text, allowing numbers to differ by `tol` (the settled keyframe's
    last digit may differ between platforms' floating-point maths)."""
    if a == b:
        return True
    if _NUMBER.sub("#", a) != _NUMBER.sub("#", b):
        return False
    na, nb = _NUMBER.findall(a), _NUMBER.findall(b)
    return all(abs(float(x) - float(y)) <= tol for x, y in zip(na, nb, strict=True))


def stale_files() -> list[Path]:
    """Committed model files that differ from what the generator produces now."""
    return [p for feet, p in MODEL_FILES.items() if not p.exists() or not xml_matches(p.read_text(), to_xml(feet))]


def to_xml(feet: str = "caster", params: ModelParams | None = None) -> str:
    spec = build_spec(feet, params)
    spec.compile()
    return spec.to_xml()


def load_model(feet: str = "caster", params: ModelParams | None = None) -> mujoco.MjModel:
    """Compile a model directly from the generator (used by tests and parameter sweeps)."""
    return build_spec(feet, params).compile()


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--check", action="store_true", help="only check that the committed files are current")
    args = parser.parse_args(argv)
    if not args.check:
        for feet, path in MODEL_FILES.items():
            path.parent.mkdir(parents=True, exist_ok=True)
            path.write_text(to_xml(feet))
            print(f"wrote {path.relative_to(REPO_ROOT)}")
        return 0
    stale = stale_files()
    if stale:
        print("out of date: " + ", ".join(str(p) for p in stale))
        print("regenerate with: python -m legged_casters.robot.build")
        return 1
    print("model files are up to date")
    return 0


if __name__ == "__main__":
    sys.exit(main())
