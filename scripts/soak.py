"""Soak and start-up tests of the robot side: the bridge against a robot, for a long time
or many times, with a CPU load beside it.

    python scripts/soak.py --minutes 60                    # sim robot + bridge + random operator
    python scripts/soak.py --minutes 60 --rt-priority 20   # the same under SCHED_FIFO
    python scripts/soak.py --starts 200                    # 200 bridge starts through the stand-up

**Soak** (``--minutes``): ``sim_robot`` (the caster Go2, MuJoCo at 2 ms, real time) and
``bridge`` (the shipped caster policy by default) run as their own processes, with the
bridge's default safety limits (staleness 1.5 control periods); this process is the
operator: a random velocity command and propulsion mode every ``--command-every``
seconds, published at 10 Hz. After a fault (the bridge latched DAMPING) it waits a
second and sends a reset, so the soak goes on and every fault is counted. Beside them
runs ``--load``: ``cpu`` (one busy process per core, normal priority), ``train`` (a
caster_omni training run) or ``none``. Printed every ``--report-every`` seconds and at
the end: stale-state and other faults, rejected messages, the state -> command latency
(from the state's timestamp, the sim's scheduled step time on CLOCK_MONOTONIC, to the
command's arrival here) p50 / p99 / max, missed periods (states the running bridge
never answered), falls of the simulated robot, and each process's RSS growth (MB per
hour, from the end of the first minute to the end). Exit status 1 if a process died.

**Starts** (``--starts N``): N fresh bridge processes, one after the other. This process
plays the robot: a standing state at ``--state-hz`` (default: the control rate; a Go2 sends 500) on
absolute deadlines (stamped with the deadline) from the moment the bridge's first status
arrives, through the linear stand-up (``--standup linear --standup-time``: these states
do not move, so the fold stand-up would only take longer) and ``--run-seconds`` of
policy. Counted: starts whose bridge latched a fault; per start, the worst state ->
command latency (from this process's put of the state to the arrival of the command
that answers it) and when it came, after the first command and after the bridge's first
status with step statistics (rate and jitter, from the stand-up's second step on), and where
it went (the state's transport to the bridge, the bridge's step, the way back: each bridge
runs with ``--trace``); and over all starts the steady-state latency (states put 0.5 s or
more after a start's first command).

Both write their logs (each process's output, a JSON summary) to ``--out``
(default: logs/soak/<date>_<mode>/).
"""

from __future__ import annotations

import argparse
import gc
import json
import math
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import zenoh

from legged_casters.deploy import protocol as P
from legged_casters.deploy import transport
from legged_casters.deploy.bench import module_cmd
from legged_casters.deploy.bridge import SHIPPED_POLICY
from legged_casters.deploy.policy import load_meta
from legged_casters.robot import go2

ROOT = Path(__file__).resolve().parents[1]
FALL_HEIGHT = 0.15
"""Trunk height (m) below which the simulated robot counts as fallen."""


def rss_mb(pid: int) -> float:
    """Resident set size of a process (MB), from /proc; nan where unreadable."""
    try:
        with open(f"/proc/{pid}/status") as f:
            for line in f:
                if line.startswith("VmRSS:"):
                    return int(line.split()[1]) / 1024.0
    except OSError:
        pass
    return math.nan


def percentiles_ms(x: list[float]) -> dict[str, float]:
    if not x:
        return {"n": 0}
    a = np.asarray(x) * 1e3
    p50, p99 = np.percentile(a, [50, 99])
    return {"n": int(a.size), "p50_ms": float(p50), "p99_ms": float(p99), "max_ms": float(a.max())}


def fmt_latency(d: dict) -> str:
    if not d.get("n"):
        return "no samples"
    return f"p50 {d['p50_ms']:.2f} ms, p99 {d['p99_ms']:.2f} ms, max {d['max_ms']:.2f} ms (n={d['n']})"


class Load:
    """Something that keeps the CPU busy beside the robot side, at normal priority."""

    def __init__(self, kind: str, out: Path):
        self.kind = kind
        self.procs: list[subprocess.Popen] = []
        if kind == "cpu":
            burn = "import signal,sys; signal.signal(signal.SIGTERM, lambda *a: sys.exit(0))\nwhile True: pass"
            for _ in range(os.cpu_count() or 1):
                self.procs.append(subprocess.Popen([sys.executable, "-c", burn]))
        elif kind == "train":
            log = open(out / "load_train.log", "w")  # noqa: SIM115 - closed with the process
            cmd = [sys.executable, str(ROOT / "train.py"), "--task", "caster_omni", "--console", "line"]
            cmd += ["--max_iterations", "100000", "--run_name", "soak_load", "--eval_every", "0"]
            self.procs.append(subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT, cwd=ROOT))
        elif kind != "none":
            raise ValueError(f"--load must be cpu, train or none, got {kind!r}")

    def stop(self) -> None:
        for p in self.procs:
            p.terminate()
        for p in self.procs:
            try:
                p.wait(timeout=10)
            except subprocess.TimeoutExpired:
                p.kill()


def start_process(name: str, cmd: list[str], out: Path) -> subprocess.Popen:
    log = open(out / f"{name}.log", "w")  # noqa: SIM115 - closed with the process
    return subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT, cwd=ROOT)


def stop_processes(procs: dict[str, subprocess.Popen]) -> None:
    for p in procs.values():
        if p.poll() is None:
            p.send_signal(signal.SIGINT)  # the deploy tools stop cleanly on Ctrl-C
    for p in procs.values():
        try:
            p.wait(timeout=10)
        except subprocess.TimeoutExpired:
            p.kill()
            p.wait()


class Monitor:
    """The harness's view of the link: states, commands, status, truth."""

    def __init__(self):
        self.lock = threading.Lock()
        self.pending: dict[int, float] = {}  # state seq -> stamp (s), not yet judged
        self.answered: dict[int, float] = {}  # state seq -> arrival of the command computed from it
        self.sent_back: dict[int, float] = {}  # state seq -> that command's stamp (the bridge's send, same clock)
        self.latency: list[float] = []
        self.missed = 0
        self.bridge_state = P.BridgeState.WAITING
        self.fault = P.Fault.NONE
        self.status: P.BridgeStatus | None = None
        self.faults: dict[str, int] = {}
        self.falls = 0
        self.fallen = False
        self.epoch: int | None = None
        self.first_cmd: float | None = None  # arrival of the first stand-up or policy command
        self.first_rate_status: float | None = None  # arrival of the first status with step statistics

    def on_state(self, sample) -> None:
        s = P.RobotState.decode(sample.payload.to_bytes())
        with self.lock:
            if s.header.epoch != self.epoch:
                self.epoch = s.header.epoch
                self.pending.clear()
                self.answered.clear()
                self.sent_back.clear()
            if self.bridge_state in (P.BridgeState.STANDUP, P.BridgeState.RUNNING):
                self.pending[s.header.seq] = s.header.stamp_ns / 1e9

    def on_cmd(self, sample) -> None:
        now = time.monotonic()
        c = P.JointCommand.decode(sample.payload.to_bytes())
        if c.mode in (P.CommandMode.POLICY, P.CommandMode.STANDUP):
            with self.lock:
                self.answered.setdefault(c.state_seq, now)
                self.sent_back.setdefault(c.state_seq, c.header.stamp_ns / 1e9)
                if self.first_cmd is None:
                    self.first_cmd = now

    def on_status(self, sample) -> None:
        now = time.monotonic()
        st = P.BridgeStatus.decode(sample.payload.to_bytes())
        with self.lock:
            if self.first_rate_status is None and st.rate_hz > 0:
                self.first_rate_status = now
            new_fault = st.fault != P.Fault.NONE and (
                st.fault != self.fault or self.bridge_state not in (P.BridgeState.DAMPING, P.BridgeState.STOPPED)
            )
            if new_fault and P.BridgeState(st.state) in (P.BridgeState.DAMPING, P.BridgeState.STOPPED):
                name = P.Fault(st.fault).name
                self.faults[name] = self.faults.get(name, 0) + 1
            self.bridge_state, self.fault, self.status = P.BridgeState(st.state), P.Fault(st.fault), st

    def on_truth(self, sample) -> None:
        t = P.SimTruth.decode(sample.payload.to_bytes())
        z = float(t.pos[2])
        with self.lock:
            if z < FALL_HEIGHT and not self.fallen:
                self.falls += 1
            self.fallen = z < FALL_HEIGHT

    def judge(self, older_than: float) -> None:
        """Move states older than `older_than` s out of `pending`: a latency if answered,
        else a missed period (unless the bridge left the running states meanwhile)."""
        now = time.monotonic()
        with self.lock:
            running = self.bridge_state in (P.BridgeState.STANDUP, P.BridgeState.RUNNING)
            for seq in [s for s, stamp in self.pending.items() if now - stamp > older_than]:
                stamp = self.pending.pop(seq)
                got = self.answered.pop(seq, None)
                if got is not None:
                    self.latency.append(got - stamp)
                elif running:
                    self.missed += 1
            # answers whose state this process never saw (before it subscribed) are dropped
            for seq in [s for s, t in self.answered.items() if now - t > 2 * older_than]:
                del self.answered[seq]


def subscribe(session, keys: dict[str, str], mon: Monitor, truth: bool) -> list:
    subs = [
        session.declare_subscriber(keys["state"], mon.on_state),
        session.declare_subscriber(keys["cmd"], mon.on_cmd),
        session.declare_subscriber(keys["status"], mon.on_status),
    ]
    if truth:
        subs.append(session.declare_subscriber(keys["truth"], mon.on_truth))
    return subs


def soak(args: argparse.Namespace, out: Path) -> int:
    meta = load_meta(args.policy)
    dt = meta.control_dt
    ns = f"soak{os.getpid()}"
    endpoint = f"tcp/127.0.0.1:{args.port}"
    rt = ["--rt-priority", str(args.rt_priority)] if args.rt_priority else []
    common = ["--namespace", ns, *rt, "--summary-every", "60"]
    load = Load(args.load, out)
    procs = {
        "bridge": start_process(
            "bridge", module_cmd("bridge", "--policy", str(args.policy), "--listen", endpoint, *common), out
        ),
    }
    time.sleep(2.0)  # the bridge listens before the robot connects
    procs["sim_robot"] = start_process(
        "sim_robot",
        module_cmd("sim_robot", "--robot", meta.robot, "--connect", endpoint, "--state-rate", f"{1 / dt:g}", *common),
        out,
    )
    transport.set_realtime(args.rt_priority)
    session = zenoh.open(transport.make_config("peer", connect=[endpoint]))
    keys = P.keys(ns)
    mon = Monitor()
    subs = subscribe(session, keys, mon, truth=True)
    op_pub = session.declare_publisher(keys["operator"])
    sender = P.Sender()
    rng = np.random.default_rng(args.seed)
    modes = [m for m in P.PropulsionMode if m.key in meta.propulsion_modes] or [P.PropulsionMode.FOUR_WHEEL]
    lim = np.asarray(args.command_range)
    command, mode = np.zeros(3), P.PropulsionMode.FOUR_WHEEL
    t0 = time.monotonic()
    t_end = t0 + args.minutes * 60.0
    t_rss = t0 + min(60.0, args.minutes * 60.0 / 4)  # RSS baseline: after start-up and warm-up
    rss0: dict[str, float] = {}
    rss_log: list[dict] = []
    next_command, next_report, next_op = t0 + 5.0, t0 + args.report_every, t0
    reset_at: float | None = None
    crashed: dict[str, int] = {}
    commands_sent = 0

    def report() -> dict:
        elapsed = time.monotonic() - t0
        with mon.lock:
            lat = percentiles_ms(mon.latency)
            st = mon.status
        rss = {name: rss_mb(p.pid) for name, p in procs.items()}
        growth = {
            name: (rss[name] - rss0[name]) / max(time.monotonic() - t_rss, 1.0) * 3600.0 if name in rss0 else math.nan
            for name in procs
        }
        rejected = {k: v for k, v in st.rejected_by_reason().items() if v} if st is not None else {}
        line = (
            f"soak {elapsed / 60:5.1f} min: bridge {mon.bridge_state.name}, faults {mon.faults or 'none'}, "
            f"rejected {rejected or 'none'}, state->command {fmt_latency(lat)}, missed periods {mon.missed}, "
            f"falls {mon.falls}, RSS " + ", ".join(f"{n} {rss[n]:.1f} MB ({growth[n]:+.2f} MB/h)" for n in procs)
        )
        print(line, flush=True)
        res = {
            "minutes": elapsed / 60.0,
            "rt_priority": args.rt_priority,
            "load": args.load,
            "policy": str(args.policy),
            "faults": dict(mon.faults),
            "stale_faults": mon.faults.get("STALE_STATE", 0),
            "rejected": rejected,
            "latency": lat,
            "missed_periods": mon.missed,
            "falls": mon.falls,
            "operator_commands": commands_sent,
            "rss_mb": rss,
            "rss_baseline_mb": rss0,
            "rss_growth_mb_per_h": growth,
            "policy_steps": st.policy_steps if st is not None else 0,
            "crashed": crashed,
        }
        rss_log.append({"t_s": elapsed, **{f"rss_{n}": v for n, v in rss.items()}})
        return res

    print(
        f"soak: {args.minutes:g} min, policy {args.policy}, load {args.load}, rt_priority {args.rt_priority}, "
        f"logs in {out}",
        flush=True,
    )
    try:
        while True:
            now = time.monotonic()
            if now >= t_end:
                break
            for name, p in procs.items():
                if p.poll() is not None and name not in crashed:
                    crashed[name] = p.returncode
                    print(f"soak: {name} exited with status {p.returncode} (see {out / (name + '.log')})", flush=True)
            if crashed:
                break
            if not rss0 and now >= t_rss:
                rss0 = {name: rss_mb(p.pid) for name, p in procs.items()}
            if now >= next_command:
                command = rng.uniform(-lim, lim)
                mode = modes[rng.integers(len(modes))]
                next_command = now + args.command_every
            flags = 0
            with mon.lock:
                faulted = mon.bridge_state in (P.BridgeState.DAMPING, P.BridgeState.STOPPED)
            if faulted and reset_at is None:
                reset_at = now + 1.0
            if reset_at is not None and now >= reset_at:
                flags, reset_at = P.OP_RESET, None
            if now >= next_op:
                vx, vy, wz = (float(v) for v in command)
                op_pub.put(P.OperatorCommand(vx, vy, wz, int(mode), flags, sender.next_header()).encode())
                commands_sent += 1
                next_op = now + 0.1
            mon.judge(older_than=0.5)
            if now >= next_report:
                report()
                next_report += args.report_every
            time.sleep(0.02)
        time.sleep(0.6)
        mon.judge(older_than=0.5)
        result = report()
    finally:
        for s in subs:
            s.undeclare()
        op_pub.undeclare()
        session.close()
        stop_processes(procs)
        load.stop()
    result["crashed"] = crashed
    (out / "summary.json").write_text(json.dumps(result, indent=2))
    (out / "rss.json").write_text(json.dumps(rss_log))
    print(f"soak: summary in {out / 'summary.json'}", flush=True)
    print_summary(result)
    return 1 if crashed else 0


def print_summary(r: dict) -> None:
    print(f"| soak, {r['minutes']:.1f} min, load {r['load']}, rt_priority {r['rt_priority']} | |")
    print("|---|---|")
    print(f"| stale-state faults | {r['stale_faults']} |")
    print(f"| all faults | {r['faults'] or 'none'} |")
    print(f"| crashes | {len(r['crashed'])} |")
    print(f"| rejected messages | {r['rejected'] or 'none'} |")
    print(f"| state -> command latency | {fmt_latency(r['latency'])} |")
    print(f"| missed periods | {r['missed_periods']} of {r['latency'].get('n', 0) + r['missed_periods']} |")
    print(f"| policy steps | {r['policy_steps']} |")
    print(f"| falls of the sim robot | {r['falls']} |")
    for name, g in r["rss_growth_mb_per_h"].items():
        print(f"| RSS {name} | {r['rss_mb'][name]:.1f} MB, growth {g:+.2f} MB/h |")


def start_worst(sent, answered, first_cmd, first_rate, steady: list[float], sent_back=None, arrived=None) -> dict:
    """One start's worst state -> command latency (put of the state to arrival of its
    answer) and when the state went out, relative to the first command and to the first
    status with step statistics (rate, jitter: the stand-up's second step or later);
    latencies 0.5 s or more after the first command go to `steady`. With `sent_back`
    (state seq -> the answering command's own stamp, the bridge's send on the same
    monotonic clock) the worst is split into the way in (put -> the bridge's send: the
    state's transport and the bridge's step) and the way back (send -> arrival); with
    `arrived` as well (state seq -> its arrival at the bridge, the bridge's --trace) the way in
    splits further into the state's transport (put -> arrival) and the bridge (arrival -> send)."""
    worst, worst_at, worst_seq = math.nan, math.nan, None
    for seq, got in answered.items():
        put = sent.get(seq)
        if put is None:
            continue
        lat = got - put
        if first_cmd is not None and put - first_cmd >= 0.5:
            steady.append(lat)
        if not lat <= worst:  # also the first (worst is nan)
            worst, worst_at, worst_seq = lat, put, seq
    nan = math.nan
    back = (sent_back or {}).get(worst_seq)
    came = (arrived or {}).get(worst_seq)
    return {
        "worst_ms": worst * 1e3,
        "worst_in_ms": (back - worst_at) * 1e3 if back is not None else nan,
        "worst_transport_ms": (came - worst_at) * 1e3 if came is not None else nan,
        "worst_bridge_ms": (back - came) * 1e3 if came is not None and back is not None else nan,
        "worst_back_ms": (worst_at + worst - back) * 1e3 if back is not None else nan,
        "worst_after_first_cmd_s": worst_at - first_cmd if first_cmd is not None else nan,
        "worst_after_rate_status_s": worst_at - first_rate if first_rate is not None else nan,
        "answered": len(answered),
    }


def read_trace(path: Path) -> dict[int, float]:
    """A bridge's --trace CSV -> state seq -> its arrival at the bridge (s, CLOCK_MONOTONIC);
    empty when the bridge wrote none (it died)."""
    if not path.is_file():
        return {}
    rows = path.read_text().splitlines()[1:]
    return {int(seq): int(arrival) / 1e9 for seq, arrival, _ in (row.split(",") for row in rows)}


def split(r: dict) -> str:
    """'in X: transport T + bridge B, back Y' of a start's worst latency (ms)."""
    return (
        f"in {r['worst_in_ms']:.2f}: transport {r['worst_transport_ms']:.2f} + bridge {r['worst_bridge_ms']:.2f}, "
        f"back {r['worst_back_ms']:.2f}"
    )


def starts(args: argparse.Namespace, out: Path) -> int:
    """Many bridge starts through the stand-up; this process plays a standing robot."""
    meta = load_meta(args.policy)
    dt = meta.control_dt
    ns = f"starts{os.getpid()}"
    endpoint = f"tcp/127.0.0.1:{args.port}"
    load = Load(args.load, out)
    transport.set_realtime(args.robot_priority if args.robot_priority is not None else args.rt_priority)
    session = zenoh.open(transport.make_config("peer", listen=[endpoint]))
    keys = P.keys(ns)
    pub = transport.fast_publisher(session, keys["state"])
    rt = ["--rt-priority", str(args.rt_priority)] if args.rt_priority else []
    q0 = np.asarray(go2.default_joint_positions())
    rng = np.random.default_rng(args.seed)
    results = []
    steady: list[float] = []  # latencies 0.5 s or more after a start's first command, all starts
    state_dt = 1.0 / args.state_hz if args.state_hz else dt
    bridge_log = open(out / "bridges.log", "w")  # noqa: SIM115
    trace = out / "bridge_trace.csv"  # each start's bridge writes its commands' state arrivals here at its exit
    try:
        for i in range(args.starts):
            mon = Monitor()
            subs = subscribe(session, keys, mon, truth=False)
            cmd = module_cmd(
                "bridge", "--policy", str(args.policy), "--connect", endpoint, "--namespace", ns,
                "--standup", "linear", "--standup-time", f"{args.standup_time:g}", "--operator-timeout", "0",
                "--summary-every", "0", "--trace", str(trace), *rt,
            )  # fmt: skip
            bridge_log.write(f"--- start {i}\n")
            bridge_log.flush()
            t_launch = time.monotonic()
            proc = subprocess.Popen(cmd, stdout=bridge_log, stderr=subprocess.STDOUT, cwd=ROOT)
            while mon.status is None and proc.poll() is None and time.monotonic() - t_launch < 30.0:
                time.sleep(0.01)
            ready = time.monotonic() - t_launch
            sender = P.Sender()
            # This process plays a robot, whose state publisher has no garbage collector: no
            # collection pauses while it streams (it collects between starts).
            gc.collect()
            gc.disable()
            t0 = time.monotonic()
            n_steps = int(round((args.standup_time + args.run_seconds) / state_dt))
            fault_at, late = None, 0.0
            sent: dict[int, float] = {}  # state seq -> time of its put
            for k in range(n_steps):
                deadline = t0 + k * state_dt
                now = time.monotonic()
                if deadline > now:
                    time.sleep(deadline - now)
                h = sender.next_header()
                h.stamp_ns = int(deadline * 1e9)
                st = P.RobotState(
                    quat=[1.0, 0.0, 0.0, 0.0],
                    gyro=rng.normal(0, 0.02, 3),
                    q=q0 + rng.normal(0, 0.005, q0.size),
                    dq=rng.normal(0, 0.05, q0.size),
                    header=h,
                )
                payload = st.encode()
                sent[h.seq] = time.monotonic()
                pub.put(payload)
                late = max(late, time.monotonic() - deadline)
                if fault_at is None and mon.faults:
                    fault_at = deadline - t0
            gc.enable()
            with mon.lock:  # the verdict while states still flowed: the bridge goes stale once they stop
                faults, final_state = dict(mon.faults), mon.bridge_state
            time.sleep(2 * dt)
            with mon.lock:
                answered, sent_back = dict(mon.answered), dict(mon.sent_back)
                first_cmd, first_rate = mon.first_cmd, mon.first_rate_status
            mon.judge(older_than=0.0)
            for s in subs:
                s.undeclare()
            trace.unlink(missing_ok=True)
            stop_processes({"bridge": proc})
            worst = start_worst(sent, answered, first_cmd, first_rate, steady, sent_back, read_trace(trace))
            lat = percentiles_ms(mon.latency)
            res = {
                "start": i,
                "ready_s": ready,
                "faults": faults,
                "fault_after_s": fault_at,
                "final_state": final_state.name,
                # states the running bridge never answered; with --state-hz above the control rate
                # most states are not due for a step, so the count means nothing there
                "missed": mon.missed if state_dt == dt else None,
                "publish_late_max_ms": late * 1e3,
                "latency": lat,
                **worst,
                "returncode": proc.returncode,
            }
            results.append(res)
            bad = res["faults"] or final_state is not P.BridgeState.RUNNING
            if bad or (i + 1) % args.report_every_starts == 0 or i + 1 == args.starts:
                n_bad = sum(1 for r in results if r["faults"] or r["final_state"] != "RUNNING")
                print(
                    f"start {i + 1}/{args.starts}: bridge ready in {ready:.2f} s, {res['final_state']}, faults "
                    f"{res['faults'] or 'none'}"
                    + (f" {fault_at:.2f} s after the first state" if fault_at is not None else "")
                    + f", worst state->command {res['worst_ms']:.2f} ms ({split(res)}) "
                    f"{res['worst_after_first_cmd_s']:.3f} s after "
                    f"the first command ({res['worst_after_rate_status_s']:+.3f} s from the first status with step "
                    "statistics)" + f", states published up to "
                    f"{late * 1e3:.1f} ms late; so far {n_bad} of {i + 1} bad",
                    flush=True,
                )
    finally:
        pub.undeclare()
        session.close()
        load.stop()
        bridge_log.close()
    bad = [r for r in results if r["faults"] or r["final_state"] != "RUNNING"]
    n_bad = len(bad)
    # A fault after this process itself published a state late by a third of the staleness
    # limit or more is the robot side's, not the bridge's.
    limit_ms = 1.5 * dt * 1e3
    robot_late = sum(1 for r in bad if r["publish_late_max_ms"] >= limit_ms / 3)
    maxes = [r["worst_ms"] for r in results if math.isfinite(r["worst_ms"])]
    steady_p99 = float(np.percentile(steady, 99) * 1e3) if steady else math.nan
    # the worst state of a start put at most 20 ms before (a stall delays the status too) to 2 ms after the
    # arrival of the first status with step statistics
    near_status = sum(1 for r in results if -0.020 <= r["worst_after_rate_status_s"] <= 0.002)
    summary = {
        "starts": len(results),
        "bad_starts": n_bad,
        "bad_after_a_late_robot_state": robot_late,
        "stale_starts": sum(1 for r in results if "STALE_STATE" in r["faults"]),
        "rt_priority": args.rt_priority,
        "robot_priority": args.robot_priority,
        "load": args.load,
        "worst_latency_ms": max(maxes) if maxes else math.nan,
        "p99_of_start_max_ms": float(np.percentile(maxes, 99)) if maxes else math.nan,
        "median_of_start_max_ms": float(np.median(maxes)) if maxes else math.nan,
        "steady": percentiles_ms(steady),
        "steady_p99_ms": steady_p99,
        "starts_within_2ms_of_steady_p99": sum(1 for m in maxes if m <= steady_p99 + 2.0),
        # the others' worst split: put -> the state's arrival at the bridge -> its send of the answer -> arrival here
        "outside_2ms": [
            {k: r[k] for k in ("worst_ms", "worst_in_ms", "worst_transport_ms", "worst_bridge_ms", "worst_back_ms")}
            for r in results
            if math.isfinite(r["worst_ms"]) and r["worst_ms"] > steady_p99 + 2.0
        ],
        "worst_at_first_rate_status": near_status,
        "state_hz": 1.0 / state_dt,
        "results": results,
    }
    (out / "starts.json").write_text(json.dumps(summary, indent=2))
    print(
        f"starts: {len(results)} bridge starts, load {args.load}, rt_priority {args.rt_priority}: "
        f"{n_bad} ended in a fault or not RUNNING ({summary['stale_starts']} stale state; {robot_late} of them after "
        f"this process, the robot, published a state {limit_ms / 3:.0f} ms or more late); state->command: steady "
        f"{fmt_latency(summary['steady'])}; each start's worst: median {summary['median_of_start_max_ms']:.2f} ms, "
        f"p99 {summary['p99_of_start_max_ms']:.2f} ms, max {summary['worst_latency_ms']:.2f} ms, within 2 ms of the "
        f"steady p99 in {summary['starts_within_2ms_of_steady_p99']} of {len(maxes)}, at the first status with step "
        f"statistics (put 20 ms before to 2 ms after its arrival) in {near_status}; "
        + "".join(f"outside: {r['worst_ms']:.2f} ms ({split(r)}); " for r in summary["outside_2ms"])
        + f"details in {out / 'starts.json'}",
        flush=True,
    )
    return 0


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    what = p.add_mutually_exclusive_group(required=True)
    what.add_argument("--minutes", type=float, help="soak this long")
    what.add_argument("--starts", type=int, help="this many bridge starts instead of a soak")
    p.add_argument("--policy", type=Path, default=SHIPPED_POLICY, help="export directory (default: the shipped one)")
    p.add_argument("--load", choices=("cpu", "train", "none"), default="cpu", help="what runs beside (default cpu)")
    p.add_argument("--rt-priority", type=int, default=0, help="SCHED_FIFO priority of every robot-side process")
    p.add_argument("--port", type=int, default=17900)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", type=Path, default=None, help="log directory (default: logs/soak/<date>_<mode>)")
    p.add_argument("--report-every", type=float, default=60.0, help="soak: seconds between progress lines")
    p.add_argument("--command-every", type=float, default=4.0, help="soak: seconds between new random commands")
    p.add_argument(
        "--command-range", type=float, nargs=3, default=(1.0, 0.4, 0.8), metavar=("VX", "VY", "WZ"),
        help="soak: random commands uniform in +-these (m/s, m/s, rad/s)",
    )  # fmt: skip
    p.add_argument("--standup-time", type=float, default=2.0, help="starts: the bridge's --standup-time")
    p.add_argument("--run-seconds", type=float, default=1.0, help="starts: seconds of policy after the stand-up")
    p.add_argument(
        "--state-hz", type=float, default=0.0,
        help="starts: the robot's state rate (default 0: the policy's control rate; a Go2 sends 500)",
    )  # fmt: skip
    p.add_argument("--report-every-starts", type=int, default=10, help="starts: a progress line every this many")
    p.add_argument(
        "--robot-priority", type=int, default=None,
        help="starts: SCHED_FIFO priority of this process, the robot (default: --rt-priority); above the bridge's, "
        "a late state from this side cannot be what trips the bridge",
    )  # fmt: skip
    args = p.parse_args(argv)
    if args.minutes is not None and args.minutes <= 0:
        p.error("--minutes must be > 0")
    if args.starts is not None and args.starts < 1:
        p.error("--starts must be >= 1")
    try:
        load_meta(args.policy)
    except Exception as e:  # noqa: BLE001 - any unusable export: say so before starting processes
        p.error(f"--policy {args.policy}: {e}")
    mode = "soak" if args.minutes is not None else "starts"
    out = args.out or ROOT / "logs" / "soak" / f"{time.strftime('%Y-%m-%d_%H-%M-%S')}_{mode}"
    out.mkdir(parents=True, exist_ok=True)
    return soak(args, out) if mode == "soak" else starts(args, out)


if __name__ == "__main__":
    sys.exit(main())
