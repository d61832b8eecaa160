"""What every robot side of the protocol does the same way (sim_robot, fake_go2,
go2_adapter; docs/protocol.md "Writing a robot side"): take joint commands in, decide
what to apply under the watchdog, run a fixed-rate loop, and print its status."""

from __future__ import annotations

import threading
import time
from collections.abc import Callable

import numpy as np

from legged_casters.deploy import protocol as P
from legged_casters.deploy import transport


class CommandInbox:
    """The command input: each JointCommand is decoded, checked against the robot's joint
    count and the stream's sequence filter, and kept as the newest with its arrival
    time; accepted and rejected messages are counted, and the state -> command round
    trip is timed. Thread-safe (commands arrive in the transport's thread)."""

    def __init__(self, n: int):
        self.n = n
        self._lock = threading.Lock()
        self._cmd: P.JointCommand | None = None
        self._arrival = 0.0
        self.filter = P.SequenceFilter()
        self.rejected = dict.fromkeys(P.REJECT_REASONS, 0)
        self.received = 0
        self.round_trip = P.RoundTrip()

    def on_payload(self, payload: bytes) -> None:
        now = time.monotonic()
        try:
            msg = P.JointCommand.decode(payload)
            if len(msg.q) != self.n:
                raise P.ProtocolError("malformed", f"command for {len(msg.q)} joints, this robot has {self.n}")
            with self._lock:
                self.filter.check(msg.header)
        except P.ProtocolError as e:
            self.reject(e.reason)
            return
        self.round_trip.answered(msg.state_seq, now)
        self.accept(msg, now)

    def reject(self, reason: str) -> None:
        with self._lock:
            self.rejected[reason] += 1

    def accept(self, msg: P.JointCommand, now: float) -> None:
        """Make a checked command the newest (and restart the watchdog)."""
        with self._lock:
            self._cmd, self._arrival = msg, now
            self.received += 1

    def latest(self) -> tuple[P.JointCommand | None, float]:
        """(newest command or None, its arrival time)."""
        with self._lock:
            return self._cmd, self._arrival


class TakesCommands:
    """The bridge-facing side of a robot side that keeps its commands in `self.inbox` (a
    CommandInbox): the transport's callback and the counts the status lines print."""

    inbox: CommandInbox

    def on_command(self, payload: bytes) -> None:
        self.inbox.on_payload(payload)

    @property
    def rejected(self) -> dict[str, int]:
        return self.inbox.rejected

    @property
    def commands_received(self) -> int:
        return self.inbox.received


WATCHDOG_WHY = "no command for the watchdog time"


def command_targets(cmd: P.JointCommand, arrival: float, now: float, watchdog: float, damping_kd, rest_q):
    """(mode, why, q, dq, kp, kd) to apply for the newest command: damping (kp 0, dq 0,
    kd `damping_kd`, q `rest_q`) once it is older than `watchdog` seconds; a damping
    command's own kd with kp 0; else the command's targets and gains."""
    n = len(rest_q)
    zeros = np.zeros(n)
    if now - arrival > watchdog:
        return P.CommandMode.DAMPING, WATCHDOG_WHY, rest_q, zeros, zeros, np.broadcast_to(damping_kd, (n,))
    q, kd = np.asarray(cmd.q), np.asarray(cmd.kd)
    if cmd.mode == P.CommandMode.DAMPING:
        return P.CommandMode.DAMPING, "damping commanded", q, zeros, zeros, kd
    dq = np.asarray(cmd.dq) if cmd.dq is not None else zeros
    return P.CommandMode(cmd.mode), "", q, dq, np.asarray(cmd.kp), kd


def run_fixed_rate(period: float, running: Callable[[], bool], step: Callable[[float, float], None],
                   on_overrun: Callable[[], None] | None = None) -> None:  # fmt: skip
    """Call step(now, deadline) at the absolute deadlines t0 + k period (sleeping in
    between) while running(); more than 50 ms behind, it gives up catching up and
    restarts the deadlines from now (on_overrun is told)."""
    t0, k = time.monotonic(), 0
    while running():
        deadline = t0 + k * period
        now = time.monotonic()
        if deadline > now:
            time.sleep(deadline - now)
            now = time.monotonic()
        elif now - deadline > 0.05:
            if on_overrun is not None:
                on_overrun()
            t0, k = now, 0
            deadline = now
        step(now, deadline)
        k += 1


class Watch:
    """The live status of a robot-side process: a line per mode change ('prog: OLD -> NEW
    (why)') from a list of (time, mode, why) that the process appends to, and a
    periodic summary."""

    def __init__(self, prog: str, changes: list):
        self.prog, self.changes, self.seen = prog, changes, 1

    def report(self) -> None:
        """Print the changes not printed yet."""
        changes = list(self.changes)
        for k in range(self.seen, len(changes)):
            why = f" ({changes[k][2]})" if changes[k][2] else ""
            print(f"{self.prog}: {changes[k - 1][1].name} -> {changes[k][1].name}{why}", flush=True)
        self.seen = max(self.seen, len(changes))

    def serve(self, duration: float, summary_every: float, summary: Callable[[float], None],
              close: Callable[[], None], tick: Callable[[float], None] | None = None) -> None:  # fmt: skip
        """A robot side's main loop, with the stop signals armed (a signal that came before
        ends it at once): until `duration` s have passed (0: until Ctrl-C or SIGTERM, which
        return normally), every 0.2 s report the changes and call tick(seconds since start);
        every `summary_every` s (0: never) call summary(seconds since the last summary).
        However it ends, close() and then the last changes."""
        t0 = time.monotonic()
        t_end = t0 + duration if duration > 0 else float("inf")
        last = t0
        try:
            transport.arm_signals()
            while time.monotonic() < t_end:
                time.sleep(min(0.2, max(0.0, t_end - time.monotonic())))
                self.report()
                now = time.monotonic()
                if tick is not None:
                    tick(now - t0)
                if summary_every > 0 and now - last >= summary_every:
                    summary(now - last)
                    last = now
        except KeyboardInterrupt:
            pass
        finally:
            close()
            self.report()


class Rates:
    """Per-second rates of counters between calls: rates(a, b) -> [da/dt, db/dt]."""

    def __init__(self):
        self._last: tuple | None = None

    def __call__(self, seconds: float, *counts: int) -> list[float]:
        last = self._last or (0,) * len(counts)
        self._last = counts
        return [(c - p) / max(seconds, 1e-9) for c, p in zip(counts, last, strict=True)]
