"""How hard can the caster robot brake, and how steep a slope can it hold, with its legs alone?

    python research/scripts/brake_limit.py            # about 2 min on 2 cores

No policy: the skating prior of legged_casters/envs/gait.py alone (as scripts/top_speed.py),
pushing against the motion, over a grid of its frequency, amplitude and tilt.

* Brake: the trunk starts at 1.5 m/s forwards (or backwards) and the prior pushes the other
  way; measured: the time and path until the speed first falls below 0.1 m/s (the stop
  check's rest speed), and the mean deceleration over that time. Coasting (amplitude 0) is
  the reference.
* Hold: on ground tilted by 3 and 5 deg, from rest, the prior pushes uphill; measured: the
  mean velocity along the uphill direction over the last 2 s of 5 s (>= 0: it holds or
  climbs).
"""

from __future__ import annotations

import argparse
import itertools
import sys
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "scripts"))
import top_speed  # noqa: E402

from legged_casters.tools.evaluate import REST_SPEED as REST  # noqa: E402  (the stop checks' rest speed)


def brake(task: str, params: list[dict], forwards: bool, seconds: float) -> list[tuple[float, float] | None]:
    """(time s, path m) to fall below REST from 1.5 m/s, per parameter set (inf: never;
    None: the robot fell)."""
    push = (-1.0, 0.0) if forwards else (1.0, 0.0)  # the prior pushes against the motion
    trace: list[torch.Tensor] = []
    _, _, fell, _ = top_speed.rollout(task, push, params, seconds, 1.0, initial_speed=-1.5, trace=trace)
    v = -torch.stack(trace)  # (steps, n): speed along the motion
    dt = seconds / len(trace)
    out = []
    for i in range(len(params)):
        if fell[i]:
            out.append(None)
            continue
        below = (v[:, i] < REST).nonzero().flatten()
        if len(below) == 0:
            out.append((float("inf"), float("inf")))
            continue
        k = int(below[0])
        out.append(((k + 1) * dt, float(v[: k + 1, i].clamp(min=0).sum()) * dt))
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--task", default="caster_omni")
    ap.add_argument("--frequencies", default="2,3,4")
    ap.add_argument("--amplitudes", default="0.2,0.3,0.42,0.55")
    ap.add_argument("--tilts", default="0.02,0.1,0.2")
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    floats = lambda s: [float(x) for x in s.split(",")]  # noqa: E731
    grid = [
        dict(top_speed.START, frequency=f, amplitude=a, tilt=t, thigh_share=0.0)
        for f, a, t in itertools.product(floats(args.frequencies), floats(args.amplitudes), floats(args.tilts))
    ]
    coast = [dict(top_speed.START, amplitude=0.0)]
    print("| push | frequency (Hz) | amplitude (rad) | tilt (rad) | brake from +1.5: s, m, m/s^2 | "
          "brake from -1.5: s, m, m/s^2 | uphill speed on 3 deg | on 5 deg |")  # fmt: skip
    print("|---|---:|---:|---:|---|---|---:|---:|")
    rows = coast + grid
    fwd = brake(args.task, rows, True, 6.0)
    back = brake(args.task, rows, False, 6.0)
    hold = {}
    for deg in (3.0, 5.0):
        speed, _, fell, _ = top_speed.rollout(args.task, (-1.0, 0.0), rows, 5.0, 2.0, slope_deg=deg)
        hold[deg] = [("fell" if f else f"{s:+.2f}") for s, f in zip(speed.tolist(), fell.tolist(), strict=True)]
    for i, p in enumerate(rows):
        cells = []
        for res in (fwd[i], back[i]):
            if res is None:
                cells.append("fell")
                continue
            t, d = res
            cells.append("never" if t == float("inf") else f"{t:.2f} s, {d:.2f} m, {(1.5 - REST) / t:.2f}")
        name = "coast" if i == 0 else "prior"
        print(f"| {name} | {p['frequency']:g} | {p['amplitude']:g} | {p['tilt']:g} | {cells[0]} | {cells[1]} | "
              f"{hold[3.0][i]} | {hold[5.0][i]} |", flush=True)  # fmt: skip
    return 0


if __name__ == "__main__":
    sys.exit(main())
