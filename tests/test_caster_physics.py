"""The single-caster rig against the paper's propulsion relation (section III)."""

import math

import numpy as np
import pytest

from legged_casters.robot import build
from legged_casters.robot.caster import ContactParams
from legged_casters.robot.caster_rig import RIG_LOAD, build_rig, measure_force, propulsion_force

PHIS = (15, 30, 45, 60, 75)


@pytest.mark.parametrize("alpha", (5, 10, 15, 20, 25))
def test_forward_force_matches_the_paper_within_5_percent(alpha):
    a = math.radians(alpha)
    for phi in PHIS:
        fx, _, normal = measure_force(a, math.radians(phi))
        assert normal == pytest.approx(RIG_LOAD, rel=0.01)
        expected = propulsion_force(RIG_LOAD, a, math.radians(phi))
        assert fx == pytest.approx(expected, rel=0.05), f"alpha={alpha} phi={phi}: {fx:.3f} N vs {expected:.3f} N"


def test_formula_reference_values():
    # Spot values of the relation itself (N = 50 N).
    assert propulsion_force(50, math.radians(20), math.radians(90)) == pytest.approx(50 * math.tan(math.radians(20)))
    assert propulsion_force(50, math.radians(20), 0.0) == 0.0
    assert propulsion_force(50, 0.0, math.radians(40)) == 0.0


def test_sign_claims():
    # alpha < 0 pushes backwards, mirroring alpha > 0.
    for phi in (20, 50, 70):
        back, _, _ = measure_force(math.radians(-15), math.radians(phi))
        fwd, _, _ = measure_force(math.radians(15), math.radians(phi))
        assert back < 0 < fwd
        assert back == pytest.approx(-fwd, rel=0.05)
    # A vertical swivel axis or an undeflected caster gives no propulsion.
    for phi in (20, 50):
        fx, _, _ = measure_force(0.0, math.radians(phi))
        assert abs(fx) < 0.01 * RIG_LOAD * 0.05
    fx, _, _ = measure_force(math.radians(20), 0.0)
    assert abs(fx) < 0.01


def test_deflection_symmetry():
    # F(+phi) = F(-phi); the lateral force changes sign with phi.
    a = math.radians(15)
    fx_pos, fy_pos, _ = measure_force(a, math.radians(40))
    fx_neg, fy_neg, _ = measure_force(a, math.radians(-40))
    assert fx_pos == pytest.approx(fx_neg, rel=0.01)
    assert abs(fy_pos) > 1.0
    assert fy_pos == pytest.approx(-fy_neg, rel=0.01)


def test_rig_uses_the_robot_contact_settings(caster_model):
    rig = build_rig(math.radians(10))
    contact = ContactParams()
    for model in (rig, caster_model):
        assert model.opt.noslip_iterations == 0  # MuJoCo Warp has no noslip solver
        assert model.opt.timestep == contact.timestep
        assert model.opt.impratio == contact.impratio
        assert model.opt.cone == caster_model.opt.cone
    rig_wheel, robot_wheel = rig.geom("rig_wheel"), caster_model.geom("FL_wheel")
    for field in ("size", "solref", "solimp", "friction", "condim", "type"):
        np.testing.assert_allclose(getattr(rig_wheel, field), getattr(robot_wheel, field))
    np.testing.assert_allclose(rig.geom("floor").solref, caster_model.geom("floor").solref)
    swivel = rig.joint("rig_caster_swivel_joint").dofadr[0]
    robot_swivel = caster_model.joint("FL_caster_swivel_joint").dofadr[0]
    assert rig.dof_armature[swivel] == caster_model.dof_armature[robot_swivel]
    assert rig.dof_damping[swivel] == caster_model.dof_damping[robot_swivel]
    assert build.MODEL_FILES["caster"].exists()
