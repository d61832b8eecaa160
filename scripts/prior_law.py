"""Measure the skating prior's speed law: open-loop speed against oscillation amplitude.

    python scripts/prior_law.py                                   # forward at tilt 0.1, backward at 0.25; ~2 min
    python scripts/prior_law.py --direction forward --tilt 0.08 --amplitudes 0.06,0.08,0.1,0.15

No policy: each robot runs caster_omni's prior alone (frequency, thigh_share and
lateral_gain as configured) at its own amplitude and the given tilt, under a saturating
command along the direction (full tilt), in the evaluation setting (no noise, pushes or
randomisation), from a stand (or, with `--initial-speed`, from a trunk already moving
that fast along the direction); `scripts/top_speed.py`'s rollout. Speed: displacement
along the direction over the last `--window` s of `--seconds`, a fall marked F.

Prints one row per amplitude and the monotone part of the table as a `gait.amplitude_law`
(forward) or `gait.amplitude_law_backward` value for `--set`: [[speed, amplitude], ...],
starting at [0, 0]. Points where the speed does not grow with the amplitude (the robot
fell, or a larger amplitude is not faster) are left out of the law.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
import top_speed  # noqa: E402  (the rollout of scripts/top_speed.py)

from legged_casters import registry  # noqa: E402

DEFAULTS = {
    "forward": (0.1, "0.05,0.06,0.07,0.08,0.09,0.1,0.12,0.13,0.15,0.18,0.2,0.22,0.25"),
    "backward": (0.25, "0.14,0.15,0.16,0.17,0.18,0.19,0.2,0.22,0.24,0.26,0.3,0.35"),
}
"""direction: (tilt rad, amplitudes rad) measured for caster_omni's speed-law prior (research/log.md)."""


def monotone_law(amplitudes, speeds, fell) -> list[list[float]]:
    """[[0, 0], [speed, amplitude], ...] over the points whose speed exceeds every smaller amplitude's."""
    law, best = [[0.0, 0.0]], 0.0
    for a, v, f in sorted(zip(amplitudes, speeds, fell, strict=True)):
        if not f and v > best + 1e-3:
            law.append([round(float(v), 3), round(float(a), 4)])
            best = v
    return law


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--direction", choices=("forward", "backward", "both"), default="both")
    ap.add_argument("--tilt", type=float, help="swivel-axis tilt (rad; default: forward 0.1, backward 0.25)")
    ap.add_argument("--amplitudes", help="comma-separated amplitudes (rad; default: a grid per direction)")
    ap.add_argument("--seconds", type=float, default=12.0)
    ap.add_argument("--window", type=float, default=3.0)
    ap.add_argument(
        "--initial-speed", type=float, default=0.0,
        help="m/s along the direction at the start instead of a stand (does the speed depend on where it starts?)",
    )  # fmt: skip
    args = ap.parse_args(argv)
    if not 0 < args.window < args.seconds:
        ap.error("--window must be positive and shorter than --seconds")
    torch.set_num_threads(1)
    gait = registry.get_task("caster_omni").env_cfg.gait
    dirs = ("forward", "backward") if args.direction == "both" else (args.direction,)
    for name in dirs:
        tilt = args.tilt if args.tilt is not None else DEFAULTS[name][0]
        try:
            amps = [float(a) for a in (args.amplitudes or DEFAULTS[name][1]).split(",")]
        except ValueError:
            ap.error(f"--amplitudes: expected comma-separated numbers, got {args.amplitudes!r}")
        if tilt < 0 or any(a < 0 for a in amps):
            ap.error("--tilt and --amplitudes must be >= 0")
        base = {
            "frequency": gait.frequency, "thigh_share": gait.thigh_share, "lateral_gain": gait.lateral_gain,
            "tilt": tilt,
        }  # fmt: skip
        params = [{**base, "amplitude": a} for a in amps]
        speed, _power, fell, _mass = top_speed.rollout(
            "caster_omni", top_speed.DIRECTIONS[name], params, args.seconds, args.window, args.initial_speed
        )
        start = f", from {args.initial_speed:g} m/s" if args.initial_speed else ", from a stand"
        print(f"[prior_law] {name}, tilt {tilt:g} rad, {gait.frequency:g} Hz, thigh_share {gait.thigh_share:g}{start}:")
        for a, v, f in zip(amps, speed, fell, strict=True):
            print(f"    amplitude {a:.3f} rad: " + ("fell" if f else f"{v:+.2f} m/s"))
        key = "amplitude_law" if name == "forward" else "amplitude_law_backward"
        print(f"[prior_law] gait.{key}={monotone_law(amps, speed, fell)}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
