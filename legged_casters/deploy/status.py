"""Live status of the robot-side processes (sim_robot, fake_go2, go2_adapter): a line on
every mode change and a periodic one-line summary, from the main thread while the
work runs in others."""

from __future__ import annotations

import time
from collections.abc import Callable


def report_changes(changes: list, seen: int, prog: str) -> int:
    """Print `changes[seen:]` ((time, mode, why) tuples; the first is the start) as
    'prog: OLD -> NEW (why)'; returns the new count."""
    changes = list(changes)
    for k in range(max(seen, 1), len(changes)):
        why = f" ({changes[k][2]})" if changes[k][2] else ""
        print(f"{prog}: {changes[k - 1][1].name} -> {changes[k][1].name}{why}", flush=True)
    return len(changes)


def run(duration: float, summary_every: float, tick: Callable[[float], None], summary: Callable[[], None]) -> None:
    """Until `duration` seconds have passed (0: until Ctrl-C, which returns normally):
    tick(seconds since start) every 0.2 s, summary() every `summary_every` s (0: never)."""
    t0 = time.monotonic()
    t_end = t0 + duration if duration > 0 else float("inf")
    next_summary = t0 + summary_every
    try:
        while time.monotonic() < t_end:
            time.sleep(min(0.2, max(0.0, t_end - time.monotonic())))
            tick(time.monotonic() - t0)
            if summary_every > 0 and time.monotonic() >= next_summary:
                next_summary += summary_every
                summary()
    except KeyboardInterrupt:
        pass
