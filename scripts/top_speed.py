"""The caster robot's top open-loop speed: CMA-ES over the skating prior's parameters.

    python scripts/top_speed.py                          # forward, backward, sideways; ~6 min on 2 cores
    python scripts/top_speed.py --directions backward --generations 30

No policy: every robot's joint targets are the prior of `legged_casters/envs/gait.py`
alone (what `play.py --policy zero` would add to a zero residual), with its own
parameters (frequency, amplitude, tilt, thigh_share, and lateral_gain for sideways),
under a saturating command (1 m/s along the direction, the prior's full tilt and
amplitude). caster_omni's evaluation settings (no noise, pushes or randomisation),
flat ground, from a stand. One CMA-ES (the `cma` package) per direction; each
generation's candidates run side by side in one env. Score: the mean speed along
the direction over the last `--window` seconds of a `--seconds` rollout (world frame,
displacement / time, so a robot that veers loses speed), a fall scores -1 m/s.

Prints per direction the best parameters, their speed, mean positive mechanical
power and cost of transport, and a markdown table at the end.
"""

from __future__ import annotations

import argparse
import math
import sys
import time

import numpy as np
import torch

from legged_casters import registry
from legged_casters.envs import gait
from legged_casters.tools.evaluate import EVAL_SETTINGS

DIRECTIONS = {"forward": (1.0, 0.0), "backward": (-1.0, 0.0), "sideways": (0.0, 1.0)}
PARAMS = {  # name: (low, high)
    "frequency": (0.5, 4.0),
    "amplitude": (0.0, 0.6),
    "tilt": (0.0, 0.5),
    "thigh_share": (0.0, 1.0),
    "lateral_gain": (0.0, 2.0),
}
"""The prior's parameters searched, with their bounds (GaitPriorCfg units: Hz, rad, rad, -, -)."""
START = {"frequency": 2.0, "amplitude": 0.2, "tilt": 0.2, "thigh_share": 0.0, "lateral_gain": 1.0}
"""caster_omni's prior: the search starts there."""


def rollout(
    task: str, direction: tuple[float, float], params: list[dict], seconds: float, window: float,
    initial_speed: float = 0.0, slope_deg: float = 0.0, trace: list | None = None,
):  # fmt: skip
    """Each parameter set on its own robot; returns (speed, power, fell) arrays. With
    `initial_speed` (m/s) every trunk starts moving that fast along the direction; with
    `slope_deg` the ground rises along the direction (the push goes uphill); a `trace` list
    gets each control step's trunk velocity along the direction (world frame, (n,) each)."""
    n = len(params)
    env_cfg, _ = registry.task_configs(
        task, {**EVAL_SETTINGS, "num_envs": n, "episode_length_s": seconds + 5.0, "sim.backend": "cpu"}
    )
    env = registry.get_task(task).env_class(env_cfg)
    try:
        cmd = torch.tensor([[direction[0], direction[1], 0.0]]).repeat(n, 1)
        env.set_commands(cmd)
        env.set_mode("four_wheel")
        env.reset()
        along = torch.tensor(direction)
        if slope_deg:
            downhill = math.atan2(-direction[1], -direction[0])
            env.set_ground_slope(slope_deg, downhill)
        if initial_speed:
            qvel = env.sim.qvel.clone()
            qvel[:, 0:2] = initial_speed * torch.tensor(direction, dtype=qvel.dtype)
            env.sim.reset(None, env.sim.qpos.clone(), qvel)

        def column(key: str) -> torch.Tensor:
            return torch.tensor([p[key] for p in params], dtype=torch.float32)

        freq = column("frequency")
        amp = column("amplitude")
        per_leg = {k: column(k).unsqueeze(1) for k in ("tilt", "thigh_share", "lateral_gain")}
        g = env.cfg.gait
        mask = torch.zeros(n, 4)
        phase = torch.zeros(n)
        steps = int(round(seconds / env.dt))
        first = steps - int(round(window / env.dt))
        fell = torch.zeros(n, dtype=torch.bool)
        power = torch.zeros(n)
        start_xy = None
        for k in range(steps):
            offsets = gait._prior(
                cmd, mask, torch.sin(phase), gait.FOOT_XY, gait._SIDE, gait._FRONT,
                tilt=per_leg["tilt"], amplitude=amp, thigh_share=per_leg["thigh_share"], full_speed=g.full_speed,
                lateral_gain=per_leg["lateral_gain"], gravity=torch.zeros(n, 3), uphill_gain=0.0,
                uphill_deadband=0.0, max_amplitude=0.0, velocity=torch.zeros(n, 2), speed_feedback=0.0,
                command_share=1.0, law_fwd=torch.zeros(0, 2), law_back=torch.zeros(0, 2), law_adds=False,
                tilt_backward=per_leg["tilt"], yaw_rate=torch.zeros(n), yaw_feedback=0.0, yaw_command_share=1.0,
                tilt_forward_brake=per_leg["tilt"], brake_blend_speed=1.0,
            )  # fmt: skip
            _, _, dones, _ = env.step(offsets / env.cfg.control.action_scale)
            phase = torch.remainder(phase + 2 * math.pi * freq * env.dt, 2 * math.pi)
            fell |= dones.bool()
            if trace is not None:
                trace.append(env.base_lin_vel_world[:, :2] @ along)
            if k == first:
                start_xy = env.base_pos[:, :2].clone()
            if k > first:
                power += env.positive_power()
        speed = ((env.base_pos[:, :2] - start_xy) @ along) / window
        power /= steps - first - 1
        speed[fell] = -1.0
        return speed.numpy(), power.numpy(), fell.numpy(), float(env.model.body_subtreemass[env.trunk_id])
    finally:
        env.close()


def to_params(x: np.ndarray, names: list[str]) -> dict:
    p = dict(START)
    for name, value in zip(names, x, strict=True):
        lo, hi = PARAMS[name]
        p[name] = float(lo + (hi - lo) * np.clip(value, 0.0, 1.0))
    return p


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--task", default="caster_omni")
    ap.add_argument("--directions", default="forward,backward,sideways")
    ap.add_argument("--generations", type=int, default=20)
    ap.add_argument("--popsize", type=int, default=16)
    ap.add_argument("--seconds", type=float, default=10.0, help="rollout length (s)")
    ap.add_argument("--window", type=float, default=3.0, help="speed measured over the last this many seconds")
    ap.add_argument("--sigma", type=float, default=0.25, help="CMA-ES initial step (parameters scaled to [0, 1])")
    ap.add_argument("--seed", type=int, default=1)
    args = ap.parse_args(argv)
    try:
        import cma
    except ImportError:
        print("top_speed.py needs the cma package: pip install cma (./setup.sh install has it)", file=sys.stderr)
        return 1
    dirs = [d.strip() for d in args.directions.split(",") if d.strip()]
    unknown = [d for d in dirs if d not in DIRECTIONS]
    if unknown:
        ap.error(f"unknown direction(s) {unknown}; choose from {sorted(DIRECTIONS)}")
    torch.set_num_threads(1)
    rows = []
    for name in dirs:
        direction = DIRECTIONS[name]
        names = [k for k in PARAMS if k != "lateral_gain" or direction[1] != 0.0]
        x0 = [(START[k] - PARAMS[k][0]) / (PARAMS[k][1] - PARAMS[k][0]) for k in names]
        es = cma.CMAEvolutionStrategy(
            x0, args.sigma, {"bounds": [0.0, 1.0], "popsize": args.popsize, "seed": args.seed, "verbose": -9}
        )
        best = (-math.inf, None, None)
        t0 = time.time()
        base, *_ = rollout(args.task, direction, [dict(START)], args.seconds, args.window)
        print(f"[top_speed] {name}: caster_omni's prior {base[0]:+.2f} m/s", flush=True)
        for gen in range(args.generations):
            xs = es.ask()
            cands = [to_params(np.asarray(x), names) for x in xs]
            speed, power, fell, mass = rollout(args.task, direction, cands, args.seconds, args.window)
            es.tell(xs, (-speed).tolist())
            i = int(np.argmax(speed))
            if speed[i] > best[0]:
                best = (float(speed[i]), cands[i], float(power[i]))
            print(
                f"[top_speed] {name} gen {gen + 1}/{args.generations}: best of generation {speed[i]:+.2f} m/s, "
                f"so far {best[0]:+.2f}, falls {int(fell.sum())}/{len(cands)} ({time.time() - t0:.0f} s)",
                flush=True,
            )
        speed, params, power = best
        cot = power / (mass * 9.81 * speed) if speed > 0 else math.nan
        rows.append((name, base[0], speed, params, power, cot))
        print(f"[top_speed] {name}: {speed:.2f} m/s, power {power:.1f} W, COT {cot:.3f}, {params}", flush=True)
    print("\n| direction | caster_omni prior (m/s) | best open-loop (m/s) | power (W) | COT | "
          "frequency (Hz) | amplitude (rad) | tilt (rad) | thigh_share | lateral_gain |")  # fmt: skip
    print("|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|")
    for name, b, speed, p, power, cot in rows:
        print(
            f"| {name} | {b:.2f} | {speed:.2f} | {power:.1f} | {cot:.3f} | {p['frequency']:.2f} | "
            f"{p['amplitude']:.3f} | {p['tilt']:.3f} | {p['thigh_share']:.2f} | {p['lateral_gain']:.2f} |"
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
