"""What does a held leg pose do on its own: does it hold a slope, brake a roll, tilt the trunk?

    python research/scripts/pose_hold.py                          # about 35 s on 2 cores
    python research/scripts/pose_hold.py --pitches 0,0.1 --rolls 0.3,0.5

No policy and no oscillation: every robot stands, then its joint targets move to the stop
pose of legged_casters/envs/gait.py (`stop_pose(pitch, roll)`, calf offset pitch x the leg's
end, hip offset roll x its side) at the prior's stop rate (a share 0.2 of the remaining way
per control step), and hold it. Evaluation settings (no noise, pushes or randomisation).

* Hold: from rest on ground tilted by --slopes deg, falling towards the nose, the tail or the
  left side; measured: how far the trunk moves in --seconds and its nose-up tilt at the end.
* Brake: on the flat the trunk starts at each of --speeds (m/s) with the pose already held;
  measured: when its speed first falls below the stop checks' rest speed, and from when on it
  stays below.
"""

from __future__ import annotations

import argparse
import itertools
import math
import sys

import torch

from legged_casters import registry
from legged_casters.envs import gait
from legged_casters.tools.evaluate import EVAL_SETTINGS
from legged_casters.tools.evaluate import REST_SPEED as REST
from legged_casters.utils.math import wrap_to_pi

DOWNHILL = {"nose": 0.0, "tail": math.pi, "side": math.pi / 2}
"""World yaw the ground falls towards, per case (the trunk starts facing +x)."""


def run(task: str, poses: list[tuple[float, float]], seconds: float, slope_deg: float = 0.0,
        downhill: float = 0.0, speed: float = 0.0, swivels: torch.Tensor | None = None):  # fmt: skip
    """One robot per pose: (moved m, final nose-up tilt deg, fell, (time the speed first falls
    below REST, time from which it stays there) s, swivel angles before and after deg) per
    pose. `swivels` (n, 4) rad: the casters' swivel angles at the start (None: the stand's)."""
    n = len(poses)
    cfg, _ = registry.task_configs(
        task, {**EVAL_SETTINGS, "num_envs": n, "episode_length_s": seconds + 5.0, "sim.backend": "cpu"}
    )
    env = registry.get_task(task).env_class(cfg)
    try:
        env.set_commands(torch.zeros(n, 3))
        env.set_mode("four_wheel")
        env.reset()
        if slope_deg:
            env.set_ground_slope(slope_deg, downhill)
        if swivels is not None:
            qpos = env.sim.qpos.clone()
            qpos[:, env.swivel_qadr] = swivels.to(qpos.dtype)
            env.sim.reset(None, qpos, env.sim.qvel.clone())
        target = torch.stack([gait.stop_pose(p, r) for p, r in poses]) / cfg.control.action_scale
        action = torch.zeros(n, 12)
        rate = cfg.gait.stop_rate
        if speed:
            for _ in range(int(round(1.0 / env.dt))):  # take the pose at rest, then launch
                action = action + rate * (target - action)
                env.step(action)
            qvel = env.sim.qvel.clone()
            qvel[:, 0] = speed
            env.sim.reset(None, env.sim.qpos.clone(), qvel)
        start = env.base_pos[:, :2].clone()
        swivel0 = _swivel_deg(env)
        fell = torch.zeros(n, dtype=torch.bool)
        rest = torch.full((n,), math.inf)
        settled = torch.zeros(n)  # the last time the speed was at or above REST
        for k in range(int(round(seconds / env.dt))):
            action = action + rate * (target - action)
            _, _, dones, _ = env.step(action)
            fell |= dones.bool()
            slow = (env.base_lin_vel_world[:, 0].abs() < REST) & torch.isinf(rest)
            rest[slow] = (k + 1) * env.dt
            settled[env.base_lin_vel_world[:, 0].abs() >= REST] = (k + 1) * env.dt
        moved = (env.base_pos[:, :2] - start).norm(dim=1)
        nose_up = torch.rad2deg(torch.asin(-env.projected_gravity[:, 0].clamp(-1, 1)))
        return moved, nose_up, fell, (rest, settled), swivel0, _swivel_deg(env)
    finally:
        env.close()


def _draws(args, poses: list[tuple[float, float]], slopes: list[float]) -> int:
    """Each pose from `args.draws` random swivel states: the range of the trunk's nose-up tilt
    on the flat, and the most it moved (with its falls) on the flat and each slope."""
    k = args.draws
    many = [p for p in poses for _ in range(k)]
    gen = torch.Generator().manual_seed(0)
    swivels = (torch.rand(len(many), 4, generator=gen) * 2 - 1) * math.pi
    cells: dict[str, list[str]] = {}
    cases = [(0.0, "flat", 0.0)] + [
        (d, f"{d:g} deg {name} down", yaw) for d in slopes for name, yaw in DOWNHILL.items()
    ]
    for deg, name, yaw in cases:
        moved, tilt, fell, *_ = run(args.task, many, args.seconds, deg, yaw, swivels=swivels)
        moved, tilt, fell = moved.view(-1, k), tilt.view(-1, k), fell.view(-1, k)
        if deg == 0.0:
            cells["flat nose-up deg, min..max"] = [
                f"{a:+.0f}..{b:+.0f}"
                for a, b in zip(tilt.min(1).values.tolist(), tilt.max(1).values.tolist(), strict=True)
            ]
        worst, falls = moved.max(1).values.tolist(), fell.sum(1).tolist()
        cells[f"{name}: worst m (falls)"] = [
            f"{m:.2f}" + (f" ({f})" if f else "") for m, f in zip(worst, falls, strict=True)
        ]
    print(f"each pose from {k} random swivel states, {args.seconds:g} s")
    _print_table(poses, cells)
    return 0


def _print_table(poses: list[tuple[float, float]], cols: dict[str, list[str]]) -> None:
    """A markdown table: one row per pose, one column per entry of `cols`."""
    print("| pitch | roll | " + " | ".join(cols) + " |")
    print("|---:|---:|" + "---|" * len(cols))
    for i, (p, r) in enumerate(poses):
        print(f"| {p:g} | {r:g} | " + " | ".join(c[i] for c in cols.values()) + " |", flush=True)


def _swivel_deg(env) -> torch.Tensor:
    """The four caster swivel angles (n, 4), deg, wrapped to [-180, 180)."""
    return torch.rad2deg(wrap_to_pi(env.sim.qpos[:, env.swivel_qadr]))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--task", default="caster_omni")
    ap.add_argument("--pitches", default="0,0.1,0.2,0.4")
    ap.add_argument("--rolls", default="-0.3,0,0.3,0.4,0.5,0.6")
    ap.add_argument("--slopes", default="3,5")
    ap.add_argument("--seconds", type=float, default=6.0)
    ap.add_argument("--speeds", default="1.5,-1.5", help="initial speeds (m/s) of the brake columns")
    ap.add_argument("--draws", type=int, default=0,
                    help="instead of the table: each pose from this many random caster swivel angles (flat and "
                         "the slopes), the worst case printed")  # fmt: skip
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    floats = lambda s: [float(x) for x in s.split(",")]  # noqa: E731
    poses = list(itertools.product(floats(args.pitches), floats(args.rolls)))
    if args.draws:
        return _draws(args, poses, floats(args.slopes))
    cols: dict[str, list[str]] = {}
    moved, tilt, fell, _, sw0, sw1 = run(args.task, poses, args.seconds)
    cols["flat: m, nose-up deg"] = [
        "fell" if f else f"{m:.2f}, {t:+.0f}"
        for m, t, f in zip(moved.tolist(), tilt.tolist(), fell.tolist(), strict=True)
    ]
    cols["swivels FL FR RL RR (deg): stand -> pose"] = [
        " ".join(f"{x:+.0f}" for x in a) + " -> " + " ".join(f"{x:+.0f}" for x in b)
        for a, b in zip(sw0.tolist(), sw1.tolist(), strict=True)
    ]
    for deg, (name, yaw) in itertools.product(floats(args.slopes), DOWNHILL.items()):
        moved, tilt, fell, *_ = run(args.task, poses, args.seconds, deg, yaw)
        cols[f"{deg:g} deg {name} down: m"] = [
            "fell" if f else f"{m:.2f}" for m, f in zip(moved.tolist(), fell.tolist(), strict=True)
        ]
    for v in floats(args.speeds):
        _, _, fell, (rest, settled), *_ = run(args.task, poses, args.seconds, speed=v)
        cols[f"brake {v:+g}: s, for good"] = [
            "fell" if f else ("never" if math.isinf(r) else f"{r:.2f}, {t:.2f}")
            for r, t, f in zip(rest.tolist(), settled.tolist(), fell.tolist(), strict=True)
        ]
    _print_table(poses, cols)
    return 0


if __name__ == "__main__":
    sys.exit(main())
