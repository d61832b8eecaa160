"""Draw the paper's Fig. 3 (propulsive force vs swivel tilt and deflection) with the
forces measured on the simulated single-caster rig on top.

    python scripts/plot_caster_force.py [--out docs/caster_force.png]
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from legged_casters.robot.caster_rig import RIG_LOAD, measure_force, propulsion_force  # noqa: E402


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", type=Path, default=Path("docs/caster_force.png"))
    args = parser.parse_args(argv)

    alphas = (-15, 5, 10, 15, 20, 25)
    phis_line = np.linspace(-90, 90, 181)
    phis_sim = (-75, -60, -45, -30, -15, 0, 15, 30, 45, 60, 75)
    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(12, 4.8))
    colors = plt.cm.viridis(np.linspace(0, 0.9, len(alphas)))
    worst = 0.0
    total = len(alphas) * len(phis_sim)
    done = 0
    for alpha, color in zip(alphas, colors, strict=True):
        a = math.radians(alpha)
        ax1.plot(phis_line, [propulsion_force(RIG_LOAD, a, math.radians(p)) for p in phis_line], color=color)
        sim = []
        for phi in phis_sim:
            sim.append(measure_force(a, math.radians(phi))[0])
            ref = propulsion_force(RIG_LOAD, a, math.radians(phi))
            if abs(phi) >= 15 and alpha != 0:
                worst = max(worst, abs(sim[-1] - ref) / abs(ref))
            done += 1
        print(f"measured alpha = {alpha:+d} deg ({done}/{total} points)", flush=True)
        ax1.plot(phis_sim, sim, "o", color=color, label=f"alpha = {alpha} deg")
    ax1.set_xlabel("caster deflection phi (deg)")
    ax1.set_ylabel("forward force F (N)")
    ax1.set_title(f"N = {RIG_LOAD:.0f} N: formula (lines) vs MuJoCo rig (dots)")
    ax1.grid(alpha=0.3)
    ax1.legend(fontsize=8)

    alphas_line = np.linspace(-30, 30, 121)
    for phi, color in zip((15, 45, 75), ("tab:blue", "tab:orange", "tab:green"), strict=True):
        p = math.radians(phi)
        ax2.plot(alphas_line, [propulsion_force(RIG_LOAD, math.radians(a), p) for a in alphas_line], color=color)
        sim_alphas = (-25, -15, -5, 0, 5, 15, 25)
        ax2.plot(
            sim_alphas,
            [measure_force(math.radians(a), p)[0] for a in sim_alphas],
            "o",
            color=color,
            label=f"phi = {phi} deg",
        )
    ax2.set_xlabel("swivel-axis tilt alpha (deg)")
    ax2.set_ylabel("forward force F (N)")
    ax2.set_title(f"largest deviation for |phi| >= 15 deg: {100 * worst:.1f} %")
    ax2.grid(alpha=0.3)
    ax2.legend(fontsize=8)
    fig.tight_layout()
    args.out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(args.out, dpi=110)
    print(f"wrote {args.out} (largest deviation {100 * worst:.2f} %)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
