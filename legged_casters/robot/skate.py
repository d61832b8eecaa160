"""Open-loop skating: the whole-robot check of the propulsion mechanism, no learning.

The legs hold a posture that tilts every swivel axis, and the hips swing the legs
sideways in a sine (left and right legs in antiphase). The casters deflect back and
forth and, on tilted axes, turn that into a push along the tilt (paper section III):
tilted forward the robot skates forward, tilted backward it skates backward.

    python -m legged_casters.robot.skate
"""

from __future__ import annotations

import argparse
import math
import sys
from dataclasses import dataclass

import mujoco
import numpy as np

from legged_casters.robot import build, go2

GRAVITY = 9.81


@dataclass(frozen=True)
class Gait:
    amplitude: float = 0.15  # rad, hip abduction swing
    frequency: float = 1.5  # Hz
    thigh_offset: float = 0.0  # rad, added to the nominal pose of every leg
    calf_offset: float = 0.15


FORWARD = Gait(thigh_offset=0.0, calf_offset=0.15)
BACKWARD = Gait(thigh_offset=0.2, calf_offset=-0.4)


def skate(model: mujoco.MjModel, gait: Gait, duration: float = 6.0, settle: float = 2.0) -> dict[str, float]:
    """Run the gait from the stand keyframe; measure after `settle` seconds.

    Returns mean forward speed (m/s), lateral drift (m), mechanical cost of transport
    (positive joint work / (m g distance), the paper's COT_mech), the mean swivel-axis
    tilt towards +x (deg), and whether the trunk stayed up."""
    data = mujoco.MjData(model)
    mujoco.mj_resetDataKeyframe(model, data, model.key(build.STAND_KEY).id)
    nominal = np.array(go2.default_joint_positions())
    dofs = [model.joint(j).dofadr[0] for j in go2.ACTUATED_JOINTS]
    sites = [model.site(f"{leg}_caster_base").id for leg in go2.LEGS]
    mass = float(model.body_subtreemass[model.body(go2.TRUNK_BODY).id])
    offsets = np.tile([0.0, gait.thigh_offset, gait.calf_offset], 4)
    swing = np.zeros(12)
    swing[0::3] = gait.amplitude * np.array([1.0 if leg[1] == "L" else -1.0 for leg in go2.LEGS])
    work, tilts, start, upright = 0.0, [], None, True
    for _ in range(int(duration / model.opt.timestep)):
        data.ctrl[:] = nominal + offsets + swing * math.sin(2 * math.pi * gait.frequency * data.time)
        mujoco.mj_step(model, data)
        if data.time < settle:
            continue
        if start is None:
            start = (data.time, data.qpos[0], data.qpos[1])
        power = data.actuator_force * data.qvel[dofs]
        work += model.opt.timestep * float(np.clip(power, 0.0, None).sum())
        z = data.site_xmat[sites].reshape(4, 3, 3)[:, :, 2]
        tilts.append(np.degrees(np.arctan2(z[:, 0], z[:, 2])).mean())
        upright &= data.qpos[2] > 0.2
    t0, x0, y0 = start
    distance = data.qpos[0] - x0
    return {
        "speed": distance / (data.time - t0),
        "lateral_drift": data.qpos[1] - y0,
        "cot": work / (mass * GRAVITY * abs(distance)) if abs(distance) > 1e-6 else math.inf,
        "tilt_deg": float(np.mean(tilts)),
        "upright": bool(upright),
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--duration", type=float, default=10.0)
    args = parser.parse_args(argv)
    model = mujoco.MjModel.from_xml_path(str(build.MODEL_FILES["caster"]))
    print("| posture | thigh / calf offset (rad) | swivel tilt (deg) | speed (m/s) | lateral drift (m) | COT_mech |")
    print("|---|---|---:|---:|---:|---:|")
    for name, gait in (("forward", FORWARD), ("backward", BACKWARD), ("nominal", Gait(calf_offset=0.0))):
        r = skate(model, gait, args.duration)
        print(
            f"| {name} | {gait.thigh_offset:+.2f} / {gait.calf_offset:+.2f} | {r['tilt_deg']:+.1f} | "
            f"{r['speed']:+.2f} | {r['lateral_drift']:+.3f} | {r['cot']:.3f} |"
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
