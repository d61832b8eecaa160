"""Benchmark: latency from a state's publication to the joint command computed from it,
and the achieved control-rate jitter, over zenoh on loopback.

    python -m legged_casters.deploy.bench                  # synthetic robot, 20 s
    python -m legged_casters.deploy.bench --robot sim      # the MuJoCo sim robot
    python -m legged_casters.deploy.bench --policy exported/ --rt-priority 20

The bridge runs as its own process (``python -m legged_casters.deploy.bridge``) with
the given export (default: the simple test policy, which has the same input/output
sizes as a trained one) and a relaxed staleness limit (``--max-state-age-ms``,
default 200), so that a scheduling hiccup is measured instead of ending the run.
``--robot synthetic``: this process plays the robot,
publishing a standing state every control period on an absolute-deadline clock and
timing each command against the publication of the state it answers (matched by
``state_seq``). ``--robot sim``: the sim robot process publishes; the latency is then
measured from the state's timestamp (its scheduled step time on CLOCK_MONOTONIC,
shared by all processes on the machine) and includes the sim's own wake-up delay.
Jitter: deviation of the interval between consecutive policy commands from
control_dt, as received here, and as the bridge reports it in its status.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np
import zenoh

from legged_casters.deploy import certs, transport
from legged_casters.deploy import protocol as P
from legged_casters.deploy.policy import load_meta
from legged_casters.deploy.simple_policy import write_policy
from legged_casters.robot import go2


def module_cmd(module: str, *args: str) -> list[str]:
    """A deploy tool's command line (unbuffered output), started at normal priority: the
    caller may be SCHED_FIFO, and the tool goes real-time itself with --rt-priority once
    it has loaded."""
    return transport.normal_priority_cmd([sys.executable, "-u", "-m", f"legged_casters.deploy.{module}", *args])


def percentiles(x_ms: np.ndarray) -> str:
    if len(x_ms) == 0:
        return "no samples"
    p50, p99 = np.percentile(x_ms, [50, 99])
    return f"p50 {p50:.3f} ms, p99 {p99:.3f} ms, max {x_ms.max():.3f} ms (n={len(x_ms)})"


def run(args: argparse.Namespace, secure: Path | None = None) -> dict[str, float]:
    """One measurement; ``secure``: a certificate directory (legged_casters.deploy.certs)
    for mutual TLS and access control on every link, None for plain TCP."""
    tmp = None
    if args.policy is None:
        tmp = tempfile.TemporaryDirectory()
        policy_dir = Path(tmp.name)
        write_policy(policy_dir, crouch_gain=0.2, control_dt=1.0 / args.control_hz)
    else:
        policy_dir = Path(args.policy)
    meta = load_meta(policy_dir)
    dt = meta.control_dt
    port = args.port
    ns = args.namespace or f"bench{os.getpid()}"
    rt = ["--rt-priority", str(args.rt_priority)] if args.rt_priority else []
    proto = "tcp" if secure is None else "tls"
    endpoint = f"{proto}/127.0.0.1:{port}"
    sec = [] if secure is None else ["--secure", str(secure)]
    env = dict(os.environ)
    bridge = subprocess.Popen(
        module_cmd(
            "bridge",
            "--policy",
            str(policy_dir),
            "--listen",
            endpoint,
            *sec,
            "--namespace",
            ns,
            "--standup",
            "linear",
            "--standup-time",
            "0.5",
            "--operator-timeout",
            "0",
            "--max-state-age-ms",
            str(args.max_state_age_ms),
            *rt,
        ),
        env=env,
    )
    procs = [bridge]
    if args.robot == "sim":
        procs.append(
            subprocess.Popen(
                module_cmd(
                    "sim_robot",
                    "--connect",
                    endpoint,
                    *sec,
                    "--namespace",
                    ns,
                    "--state-rate",
                    str(1.0 / dt),
                    *rt,
                ),
                env=env,
            )
        )
    transport.set_realtime(args.rt_priority)
    # this process plays (or listens as) the robot
    settings = None if secure is None else transport.secure_settings(secure, "robot", ns)
    session = zenoh.open(transport.make_config("peer", connect=[endpoint], secure=settings))
    keys = P.keys(ns)
    lock = threading.Lock()
    pub_time: dict[int, float] = {}  # state seq -> publication time (monotonic s)
    answered: dict[int, float] = {}  # state seq -> arrival time of the policy command computed from it
    cmd_times: list[float] = []
    statuses: list[P.BridgeStatus] = []
    measuring = threading.Event()
    final_status = None

    def on_cmd(sample):
        now = time.monotonic()
        c = P.JointCommand.decode(sample.payload.to_bytes())
        if c.mode != P.CommandMode.POLICY or not measuring.is_set():
            return
        with lock:
            answered[c.state_seq] = now  # matched with the state's time at the end: no ordering race
            cmd_times.append(now)

    def on_state(sample):
        s = P.RobotState.decode(sample.payload.to_bytes())
        with lock:
            pub_time[s.header.seq] = s.header.stamp_ns / 1e9

    subs = [
        session.declare_subscriber(keys["cmd"], on_cmd),
        session.declare_subscriber(
            keys["status"], lambda s: statuses.append(P.BridgeStatus.decode(s.payload.to_bytes()))
        ),
    ]
    try:
        if args.robot == "sim":
            subs.append(session.declare_subscriber(keys["state"], on_state))
            time.sleep(args.warmup + 2.0)
            measuring.set()
            time.sleep(args.duration)
            measuring.clear()
            final_status = statuses[-1] if statuses else None
        else:
            pub = transport.fast_publisher(session, keys["state"])
            sender = P.Sender()
            time.sleep(1.5)  # bridge start-up (imports, policy load, zenoh connect)
            rng = np.random.default_rng(0)
            q0 = np.asarray(go2.default_joint_positions())
            t0 = time.monotonic()
            k = 0
            t_measure = t0 + args.warmup
            t_end = t_measure + args.duration
            while True:
                deadline = t0 + k * dt
                now = time.monotonic()
                if deadline > now:
                    time.sleep(deadline - now)
                if deadline >= t_end:
                    break
                if deadline >= t_measure:
                    measuring.set()
                h = sender.next_header()
                h.stamp_ns = int(deadline * 1e9)
                msg = P.RobotState(
                    quat=[1.0, 0.0, 0.0, 0.0],
                    gyro=rng.normal(0, 0.05, 3),
                    q=q0 + rng.normal(0, 0.01, 12),
                    dq=rng.normal(0, 0.1, 12),
                    header=h,
                )
                payload = msg.encode()
                with lock:
                    pub_time[h.seq] = time.monotonic()
                pub.put(payload)
                k += 1
            time.sleep(0.01)
            measuring.clear()
            final_status = statuses[-1] if statuses else None
    finally:
        for s in subs:
            s.undeclare()
        session.close()
        for p in procs:
            p.terminate()
        for p in procs:
            try:
                p.wait(timeout=5)
            except subprocess.TimeoutExpired:
                p.kill()
        if tmp is not None:
            tmp.cleanup()

    lat = np.asarray([t - pub_time[seq] for seq, t in answered.items() if seq in pub_time]) * 1e3
    periods = np.diff(np.asarray(cmd_times))
    jit = np.abs(periods - dt) * 1e3
    st = final_status
    print(
        f"bench: robot={args.robot}, control {1 / dt:.0f} Hz, {args.duration:.0f} s, rt_priority={args.rt_priority}, "
        f"link {'mutual TLS + access control' if secure is not None else 'plain TCP'}"
    )
    print(f"  state publication -> command received: {percentiles(lat)}")
    if len(periods):
        print(
            f"  command interval: mean {periods.mean() * 1e3:.3f} ms (rate {1 / periods.mean():.3f} Hz), "
            f"|interval - dt|: {percentiles(jit)}"
        )
        late = int(np.sum(periods > 1.5 * dt))
        print(f"  command intervals > 1.5 control periods (would trip the default staleness limit): {late}")
    if st is not None:
        print(
            f"  bridge status at the end: {P.BridgeState(st.state).name} ({P.Fault(st.fault).name}), "
            f"rate {st.rate_hz:.3f} Hz, jitter p99 "
            f"{st.jitter_p99_ms:.3f} ms, max {st.jitter_max_ms:.3f} ms, inference {st.inference_mean_ms:.3f} ms, "
            f"rejected {st.rejected_by_reason()}"
        )
    out = {"n": float(len(lat))}
    if len(lat):
        out.update(p50_ms=float(np.percentile(lat, 50)), p99_ms=float(np.percentile(lat, 99)), max_ms=float(lat.max()))
    if len(jit):
        out.update(jitter_p99_ms=float(np.percentile(jit, 99)), jitter_max_ms=float(jit.max()))
    return out


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--robot", choices=("synthetic", "sim"), default="synthetic")
    p.add_argument("--policy", default=None, help="export directory (default: a simple test policy)")
    p.add_argument("--control-hz", type=float, default=50.0, help="control rate of the default test policy")
    p.add_argument("--duration", type=float, default=20.0, help="measured seconds")
    p.add_argument("--warmup", type=float, default=1.0, help="seconds after the stand-up before measuring")
    p.add_argument("--port", type=int, default=17800)
    p.add_argument(
        "--max-state-age-ms",
        type=float,
        default=200.0,
        help="bridge staleness limit; relaxed (default 200 ms) so that one scheduling hiccup on a busy machine "
        "does not latch the bridge in damping and end the measurement; late commands are counted instead",
    )
    p.add_argument("--rt-priority", type=int, default=0, help="SCHED_FIFO priority for all processes (0: off)")
    p.add_argument(
        "--namespace", default=None, help="robot namespace (default: bench<pid>); that of the --secure certificates"
    )
    p.add_argument(
        "--link",
        choices=("plain", "tls", "both"),
        default=None,
        help="plain TCP, mutual TLS with access control (--secure), or both one after the other "
        "(default: tls with --secure, else plain)",
    )
    p.add_argument(
        "--secure",
        type=Path,
        default=None,
        metavar="DIR",
        help="certificates for --link tls/both (default: new ones in a temporary directory)",
    )
    args = p.parse_args(argv)
    if args.link is None:
        args.link = "plain" if args.secure is None else "tls"
    if args.secure is not None:
        try:  # the certificates' files, namespace and dates, before any process starts
            transport.secure_settings(args.secure, "robot", args.namespace or f"bench{os.getpid()}")
        except transport.SessionError as err:
            p.error(f"{err} (give --namespace the one the certificates were made for)")
    results = []
    with tempfile.TemporaryDirectory() as tmp:
        cert_dir = args.secure
        if args.link != "plain" and cert_dir is None:
            cert_dir = Path(tmp)
        links = {"plain": [None], "tls": [cert_dir], "both": [None, cert_dir]}[args.link]
        for i, secure in enumerate(links):
            if secure is not None and args.secure is None:
                certs.make_all(secure, namespace=args.namespace or f"bench{os.getpid()}")
            if i:
                args.port += 1
            results.append((secure, run(args, secure)))
    if len(results) > 1:
        print("bench: state -> command latency, same run:")
        for secure, res in results:
            name = "mutual TLS" if secure is not None else "plain TCP"
            if res.get("n", 0):
                print(
                    f"  {name:>10}: p50 {res['p50_ms']:.3f} ms, p99 {res['p99_ms']:.3f} ms, max {res['max_ms']:.3f} ms"
                )
    return 0 if all(res.get("n", 0) > 0 for _, res in results) else 1


if __name__ == "__main__":
    sys.exit(main())
