"""Starts during and after stops, wider than the evaluation's own (a probe, no training).

    python research/scripts/start_matrix.py --policy resources/policies/caster_omni
    python research/scripts/start_matrix.py --task caster_omni_stop --load_run <run> --checkpoint 1200

Drives at vx -1.0, -1.5 or -2.0 m/s for 4 s, gives a zero command for 0.6 s (the robot still
rolls: a joystick let go and pushed again) or 2.0 s, then one of vx +0.5, +1.0, -0.5, vy
+-0.4, wz +-0.8; after +1.0 and +1.5 m/s the same seven commands after 2.0 s of zero: 56 starts,
each judged like the evaluation's go-again checks (the new axis within its bar over 3-6 s after
the command, no fall). Every other argument goes to `scripts/evaluate.py` (which policy, the
physics step, latency); it prints the evaluation's table and verdict lines for these 56, then
one line: the falls and the failed starts.
"""

from __future__ import annotations

import sys

from legged_casters.tools import evaluate

COMMANDS = ((0.5, 0.0, 0.0), (1.0, 0.0, 0.0), (-0.5, 0.0, 0.0), (0.0, 0.4, 0.0), (0.0, -0.4, 0.0),
            (0.0, 0.0, 0.8), (0.0, 0.0, -0.8))  # fmt: skip
STOPS = ((-1.0, (0.6, 2.0)), (-1.5, (0.6, 2.0)), (-2.0, (0.6, 2.0)), (1.0, (2.0,)), (1.5, (2.0,)))
"""(speed before the zero command, seconds of zero command before the start)."""


def scenarios() -> tuple[evaluate.Scenario, ...]:
    return tuple(evaluate._go_again(before, after, stopped) for before, zeros in STOPS for stopped in zeros
                 for after in COMMANDS)  # fmt: skip


def main(argv: list[str]) -> int:
    if "--scenarios" in argv or "--checkpoints" in argv:
        raise SystemExit("start_matrix.py runs its own scenarios on one policy: leave out --scenarios/--checkpoints")
    evaluate.SCENARIO_SETS["stop"] = scenarios()
    found: list[tuple[str, bool, str]] = []
    verdict = evaluate.verdict

    def keep(results, task=None):
        checks = verdict(results, task)
        found[:] = checks
        return checks

    evaluate.verdict = keep
    rc = evaluate.main([*argv, "--scenarios", "stop"])
    if rc or not found:
        return rc or 1
    failed = [name.rsplit(":", 1)[0] for name, ok, _ in found if not ok]  # "go ...: vx +0.5"
    falls = sum("fall" in measured for _, _, measured in found)
    print(f"[start_matrix] {len(found)} starts: {falls} with a fall, {len(failed)} failed: {failed}")
    return rc


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
