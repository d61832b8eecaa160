"""The passive 2-DOF caster module and the contact settings it needs.

One builder (`add_caster`) is used by the robot model and by the single-caster
test rig, so the physics validated on the rig is the physics the robot trains on.

Frame conventions (the paper's section III):
* the caster base body's z axis is the swivel axis z_F (pointing away from the
  wheel), its x axis is the direction the wheel trails *away from* at phi = 0;
* the swivel hinge turns the fork about z_F by phi; at phi = 0 the wheel trails
  behind the swivel axis (towards -x of the base frame), so a robot rolling
  forward has phi ~ 0 and one rolling backward has phi ~ +-pi;
* the wheel axle is the fork's y axis.
With the swivel axis tilted towards +x by alpha, the ground reaction on a
deflected caster pushes towards +x (F > 0 for alpha > 0).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field

import mujoco


@dataclass(frozen=True)
class ContactParams:
    """Contact settings shared by the robot, the floor and the caster test rig.

    Measured on the single-caster rig and the whole robot (docs/robot.md):
    MuJoCo's default contact is far too soft for a caster (the swivel's small
    effective mass makes the constraint soft, the caster creeps); a stiff solref and
    a high impratio hold the no-slip condition without a noslip solver (MuJoCo Warp
    has none). Elliptic cones with impratio 10, or solimp dmax >= 0.99, made the
    robot explode or launch under random actions; pyramidal cones with impratio 20
    and the default solimp did not (0 of 100 trials). condim 3: torsional friction
    (condim 4/6) would carry part of the swivel moment and break the propulsion
    relation.
    """

    timestep: float = 0.002  # solref's time constant must stay >= 2 * timestep
    solref: tuple[float, float] = (0.004, 1.0)
    solimp: tuple[float, float, float, float, float] = (0.9, 0.95, 0.001, 0.5, 2.0)
    impratio: float = 20.0
    condim: int = 3
    friction: float = 1.0
    cone: str = "pyramidal"
    integrator: str = "implicitfast"
    solver: str = "newton"
    iterations: int = 20
    ls_iterations: int = 30  # MuJoCo Warp hit 10 with the pyramidal cone; 30 keeps it in step with C


@dataclass(frozen=True)
class CasterParams:
    """Dimensions and passive-joint settings of one caster (a typical 50 mm caster).

    All lengths in metres, masses in kg, angles in degrees.
    """

    wheel_radius: float = 0.025  # 50 mm wheel, the common small-caster size
    wheel_width: float = 0.018  # real tread width; used for the wheel's inertia
    contact_half_width: float = 0.002  # the collision disk: one mid-plane contact
    trail: float = 0.025  # horizontal offset swivel axis -> axle
    swivel_height: float = 0.045  # along the swivel axis, base plate -> axle
    base_mass: float = 0.03
    fork_mass: float = 0.04
    wheel_mass: float = 0.05
    # Swivel axis pitched forward from the calf axis (deg). In the loaded standing pose
    # the calf points ~44 deg forward-down, so 48 deg leaves the swivel axis tilted ~4
    # deg forward: the legs can tilt it from -21 to +55 deg with the trunk at standing
    # height, and it is off vertical (an unstable stance) so the robot stands still.
    mount_angle: float = 48.0
    swivel_damping: float = 0.03  # N m s/rad; the paper randomises U[0.01, 0.1]
    # 2e-4: below ~1.5e-4 the robot stance goes soft and the rig under-reads the
    # propulsion force by >5%; at 1e-3 and above the casters shimmy in a gait.
    swivel_armature: float = 2e-4
    wheel_damping: float = 0.0
    # Rolling resistance as Coulomb friction on the wheel axle: tau = c_rr * N * R
    # with c_rr = 0.02 (tabulated range for hard polyurethane/nylon caster wheels on
    # hard floors is about 0.01-0.03) and N = the Go2 caster robot's weight / 4.
    rolling_resistance_coeff: float = 0.02
    nominal_wheel_load: float = 38.8  # N; (15.2 kg + casters) * g / 4

    @property
    def wheel_frictionloss(self) -> float:
        return self.rolling_resistance_coeff * self.nominal_wheel_load * self.wheel_radius

    @property
    def height(self) -> float:
        """Distance from the base plate to the ground along the swivel axis at alpha = 0."""
        return self.swivel_height + self.wheel_radius

    @property
    def total_mass(self) -> float:
        return self.base_mass + self.fork_mass + self.wheel_mass

    def to_dict(self) -> dict:
        return asdict(self)


@dataclass(frozen=True)
class ModelParams:
    caster: CasterParams = field(default_factory=CasterParams)
    contact: ContactParams = field(default_factory=ContactParams)


# Collision filtering: robot geoms collide with the world, never with each other.
ROBOT_CONTYPE, ROBOT_CONAFFINITY = 0, 1
WORLD_CONTYPE, WORLD_CONAFFINITY = 1, 0


def box_inertia(mass: float, size: tuple[float, float, float]) -> list[float]:
    """Diagonal inertia of a solid box with full extents `size`."""
    x, y, z = size
    return [mass / 12 * (y * y + z * z), mass / 12 * (x * x + z * z), mass / 12 * (x * x + y * y)]


def cylinder_inertia(mass: float, radius: float, length: float, axis: int) -> list[float]:
    """Diagonal inertia of a solid cylinder whose axis is coordinate `axis`."""
    along = mass * radius * radius / 2
    across = mass * (3 * radius * radius + length * length) / 12
    out = [across, across, across]
    out[axis] = along
    return out


def apply_contact_options(spec: mujoco.MjSpec, contact: ContactParams) -> None:
    opt = spec.option
    opt.timestep = contact.timestep
    opt.impratio = contact.impratio
    opt.cone = {"elliptic": mujoco.mjtCone.mjCONE_ELLIPTIC, "pyramidal": mujoco.mjtCone.mjCONE_PYRAMIDAL}[contact.cone]
    opt.integrator = {
        "implicitfast": mujoco.mjtIntegrator.mjINT_IMPLICITFAST,
        "euler": mujoco.mjtIntegrator.mjINT_EULER,
    }[contact.integrator]
    opt.solver = {"newton": mujoco.mjtSolver.mjSOL_NEWTON, "cg": mujoco.mjtSolver.mjSOL_CG}[contact.solver]
    opt.iterations = contact.iterations
    opt.ls_iterations = contact.ls_iterations
    opt.noslip_iterations = 0  # MuJoCo Warp has no noslip solver; never rely on it


def set_contact(geom: mujoco.MjsGeom, contact: ContactParams, robot: bool = True) -> None:
    geom.solref = list(contact.solref)
    geom.solimp = list(contact.solimp)
    geom.condim = contact.condim
    geom.friction = [contact.friction, 0.0, 0.0]
    geom.contype = ROBOT_CONTYPE if robot else WORLD_CONTYPE
    geom.conaffinity = ROBOT_CONAFFINITY if robot else WORLD_CONAFFINITY


def add_floor(spec: mujoco.MjSpec, contact: ContactParams, material: str = "") -> mujoco.MjsGeom:
    floor = spec.worldbody.add_geom(name="floor", type=mujoco.mjtGeom.mjGEOM_PLANE, size=[0, 0, 0.05])
    if material:
        floor.material = material
    set_contact(floor, contact, robot=False)
    return floor


def add_caster(
    parent: mujoco.MjsBody,
    prefix: str,
    pos: list[float],
    pitch: float,
    caster: CasterParams,
    contact: ContactParams,
) -> mujoco.MjsBody:
    """Attach a caster to `parent`; returns the caster base body.

    `pos` is the base plate's origin in the parent frame and `pitch` (rad) rotates
    the base about the parent's y axis, so the swivel axis is the parent's z axis
    pitched by `pitch`. Bodies: {prefix}_caster_base, {prefix}_caster_fork,
    {prefix}_wheel. Joints: {prefix}_caster_swivel_joint, {prefix}_caster_wheel_joint.
    """
    half = pitch / 2
    base = parent.add_body(name=f"{prefix}_caster_base", pos=pos, quat=[math.cos(half), 0, math.sin(half), 0])
    plate = (0.04, 0.04, 0.006)
    base.mass = caster.base_mass
    base.ipos = [0, 0, 0]
    base.inertia = box_inertia(caster.base_mass, plate)
    base.explicitinertial = True
    g = base.add_geom(name=f"{prefix}_caster_plate", type=mujoco.mjtGeom.mjGEOM_BOX, size=[p / 2 for p in plate])
    g.rgba = [0.55, 0.55, 0.6, 1]
    set_contact(g, contact)
    base.add_site(name=f"{prefix}_caster_base", pos=[0, 0, 0], size=[0.005, 0, 0])

    fork = base.add_body(name=f"{prefix}_caster_fork", pos=[0, 0, 0])
    sw = fork.add_joint(
        name=f"{prefix}_caster_swivel_joint",
        type=mujoco.mjtJoint.mjJNT_HINGE,
        axis=[0, 0, 1],
        damping=caster.swivel_damping,
        armature=caster.swivel_armature,
    )
    del sw
    # Fork: a swivel housing and an arm from the swivel down and back to the axle.
    arm_len = math.hypot(caster.trail, caster.swivel_height - 0.006)
    arm_pitch = math.atan2(caster.trail, caster.swivel_height - 0.006)
    fork.mass = caster.fork_mass
    fork.ipos = [-caster.trail / 2, 0, -caster.swivel_height / 2]
    fork.inertia = box_inertia(
        caster.fork_mass, (caster.trail + 0.01, caster.wheel_width + 0.008, caster.swivel_height)
    )
    fork.explicitinertial = True
    housing = fork.add_geom(
        name=f"{prefix}_caster_housing",
        type=mujoco.mjtGeom.mjGEOM_CYLINDER,
        size=[0.012, 0.004, 0],
        pos=[0, 0, -0.007],
    )
    qa = arm_pitch / 2
    plates = []
    for side in (-1.0, 1.0):
        plates.append(
            fork.add_geom(
                name=f"{prefix}_caster_arm_{'left' if side > 0 else 'right'}",
                type=mujoco.mjtGeom.mjGEOM_BOX,
                size=[0.005, 0.0015, arm_len / 2 - 0.002],
                pos=[-caster.trail / 2, side * (caster.wheel_width / 2 + 0.003), -(caster.swivel_height + 0.006) / 2],
                quat=[math.cos(qa), 0, math.sin(qa), 0],
            )
        )
    for geom in (housing, *plates):
        geom.rgba = [0.7, 0.7, 0.72, 1]
        set_contact(geom, contact)
    # The side plates stop short of the axle, so they stay clear of the floor for
    # any swivel angle at tilts below ~40 deg.

    wheel = fork.add_body(name=f"{prefix}_wheel", pos=[-caster.trail, 0, -caster.swivel_height])
    wheel.add_joint(
        name=f"{prefix}_caster_wheel_joint",
        type=mujoco.mjtJoint.mjJNT_HINGE,
        axis=[0, 1, 0],
        damping=caster.wheel_damping,
        frictionloss=caster.wheel_frictionloss,
    )
    wheel.mass = caster.wheel_mass
    wheel.ipos = [0, 0, 0]
    wheel.inertia = cylinder_inertia(caster.wheel_mass, caster.wheel_radius, caster.wheel_width, axis=1)
    wheel.explicitinertial = True
    # A thin disk (ellipsoid R x w x R, short axis on the axle) touches the floor at a
    # single point in the wheel's mid-plane, which the propulsion relation assumes.
    tire = wheel.add_geom(
        name=f"{prefix}_wheel",
        type=mujoco.mjtGeom.mjGEOM_ELLIPSOID,
        size=[caster.wheel_radius, caster.contact_half_width, caster.wheel_radius],
    )
    tire.rgba = [0.15, 0.15, 0.15, 1]
    set_contact(tire, contact)
    # A visual-only tread shows the real wheel width.
    tread = wheel.add_geom(
        name=f"{prefix}_wheel_visual",
        type=mujoco.mjtGeom.mjGEOM_CYLINDER,
        size=[caster.wheel_radius * 0.98, caster.wheel_width / 2, 0],
        quat=[math.cos(math.pi / 4), math.sin(math.pi / 4), 0, 0],
        contype=0,
        conaffinity=0,
        group=1,
        rgba=[0.2, 0.2, 0.25, 1],
    )
    tread.mass = 0
    # A small marker on the rim makes wheel rotation visible in videos.
    wheel.add_geom(
        type=mujoco.mjtGeom.mjGEOM_BOX,
        size=[0.003, caster.wheel_width / 2 + 0.0005, 0.003],
        pos=[caster.wheel_radius * 0.8, 0, 0],
        contype=0,
        conaffinity=0,
        group=1,
        rgba=[0.9, 0.6, 0.1, 1],
    )
    return base
