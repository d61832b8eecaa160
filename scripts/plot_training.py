"""Plot training curves of runs from their TensorBoard events, and print start/end values.

python scripts/plot_training.py logs/go2_flat/<run> logs/caster_omni/<run> --out docs/training_curves.png
python scripts/plot_training.py logs/caster_omni/<old> logs/caster_omni/<new> --x minutes --max-minutes 12

`--x minutes` puts the wall time since the run's first logged iteration on the x axis (to
compare settings at equal wall time); `--max-minutes` cuts each run there.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
from tensorboard.backend.event_processing.event_accumulator import EventAccumulator  # noqa: E402

TAGS = (
    ("Train/mean_reward", "mean episode return (mean + noise)"),
    ("Train/mean_episode_length", "mean episode length (steps)"),
    ("Episode_Reward/tracking_lin_vel", "linear-velocity tracking reward (per s)"),
    ("Eval/vx_error", "deterministic |vx error| (m/s)"),
    ("Eval/vy_error", "deterministic |vy error| (m/s)"),
    ("Eval/wz_error", "deterministic |wz error| (rad/s)"),
)
"""Panels; a run without a tag (older runs have no Eval/) leaves that panel to the others."""


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("runs", nargs="+", type=Path)
    p.add_argument("--out", type=Path, default=Path("docs/training_curves.png"))
    p.add_argument("--window", type=int, default=10, help="iterations averaged for the start/end values")
    p.add_argument("--x", choices=("iteration", "minutes"), default="iteration", help="x axis")
    p.add_argument("--max-minutes", type=float, help="only the events of each run's first this many minutes")
    args = p.parse_args(argv)
    fig, axes = plt.subplots(2, (len(TAGS) + 1) // 2, figsize=(4.2 * ((len(TAGS) + 1) // 2), 7.2))
    axes = axes.flatten()
    for run in args.runs:
        if not run.is_dir():
            print(f"no run folder {run}", file=sys.stderr)
            return 2
        acc = EventAccumulator(str(run))
        acc.Reload()
        label = f"{run.parent.name}/{run.name}"
        scalars = acc.Tags()["scalars"]
        t0 = min(acc.Scalars(t)[0].wall_time for t in scalars if acc.Scalars(t)) if scalars else 0.0
        for ax, (tag, title) in zip(axes, TAGS, strict=True):
            if tag not in scalars:
                continue
            events = acc.Scalars(tag)
            if args.max_minutes is not None:
                events = [e for e in events if e.wall_time - t0 <= args.max_minutes * 60.0]
            if not events:
                continue
            minutes = args.x == "minutes"
            steps = [(e.wall_time - t0) / 60.0 if minutes else e.step for e in events]
            values = [e.value for e in events]
            ax.plot(steps, values, label=f"{run.parent.name}/{run.name.split('_', 2)[-1]}")
            ax.set_title(title, fontsize=10)
            ax.set_xlabel("minutes of training" if minutes else "iteration")
            ax.grid(alpha=0.3)
            w = args.window
            start, end = sum(values[:w]) / len(values[:w]), sum(values[-w:]) / len(values[-w:])
            print(f"{label} {tag}: first {w} points {start:.3f} -> last {w} points {end:.3f} ({len(values)} points)")
    axes[0].legend(fontsize=8)
    fig.tight_layout()
    args.out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(args.out, dpi=100)
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
