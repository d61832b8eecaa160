"""The robot side of the bridge on a real Go2: Unitree's low-level DDS interface <-> our
zenoh wire protocol (docs/protocol.md).

    # on the robot's computer, or a PC on the robot's Ethernet (the Go2's sport mode off):
    python -m legged_casters.deploy.go2_adapter --network-interface eth0 --real-robot \\
        --listen tcp/0.0.0.0:7447
    # first, without moving anything: forwards states, logs what it would send
    python -m legged_casters.deploy.go2_adapter --network-interface eth0 --dry-run --listen tcp/0.0.0.0:7447

What it does:

* ``rt/lowstate`` (LowState_) -> ``<ns>/state`` (RobotState): IMU quaternion and gyro,
  q / dq of our joints read from Unitree's motor slots (go2.UNITREE_MOTOR; printed at
  start), stamped with this computer's monotonic clock on arrival; every
  ``--state-every``-th LowState (default 1: all of them). ``robot_mode`` is what the
  adapter is sending. A LowState with a non-finite value or a quaternion that is not
  unit is dropped and counted.
* ``<ns>/cmd`` (JointCommand) -> ``rt/lowcmd`` (LowCmd_): checked like sim_robot checks
  it (decode, joint count, sequence filter), then the newest command is written at
  ``--cmd-rate`` (default 500 Hz), every driven motor in servo mode with the command's
  q, dq, kp, kd and tau 0, unused slots off, head/level_flag as Unitree's examples set
  them, and the CRC the robot checks.
* Its own watchdog: no valid command for ``--watchdog-ms`` (default 100) -> it writes
  damping (kp 0, kd ``--damping-kd``) until commands resume, from the first LowCmd tick
  past the limit: the first damping LowCmd leaves between ``--watchdog-ms`` and one
  ``--cmd-rate`` period later (100-102 ms at the defaults, plus this process's
  scheduling delay), timed from the last command's arrival here; the summary lines
  give the measured figure. Before the first command it writes nothing, so the robot
  keeps whatever it was doing.
* Safety: on any interface other than loopback it refuses to start unless told
  ``--real-robot`` (or ``--dry-run``, which never writes ``rt/lowcmd``).
* Live status: a line on every change of what it sends (NONE -> STANDUP -> POLICY,
  -> DAMPING with the reason) and a summary every ``--summary-every`` seconds.
* ``--remote`` (with ``--policy`` or ``--task`` for the command ranges): the Go2's own
  remote, read from ``LowState.wireless_remote``, drives: its sticks and mode buttons
  become operator commands on ``<ns>/operator`` (``--remote-rate`` Hz while the remote
  reports), and its stop combination (L2+B) makes the adapter damp by itself from the
  next LowCmd on (within one ``--cmd-rate`` period of the LowState that carries it),
  with or without a bridge, and tells the bridge to stop. Only the remote's reset
  combination (L2+start) releases that stop, and the adapter then keeps damping until
  the bridge sends a stand-up. docs/driving.md has the button map.
"""

from __future__ import annotations

import argparse
import math
import sys
import threading
import time

import numpy as np

from legged_casters.deploy import drive, robot_side, transport, unitree
from legged_casters.deploy import protocol as P
from legged_casters.robot import go2

LOOPBACK = ("lo", "lo0")
REMOTE_STOP_WHY = "stop on the Go2 remote"
REMOTE_RESUME_WHY = "after a remote stop: waiting for the bridge's stand-up"
REMOTE_FRESH = 0.1
"""s: remote data older than this (no LowState) is gone: no more operator commands."""


class Go2Adapter(robot_side.TakesCommands):
    """Both directions and the watchdog; `publish_state(bytes)` sends a RobotState,
    `write_lowcmd(LowCmd)` writes to the robot (None: dry run)."""

    def __init__(
        self,
        sdk: unitree.Sdk,
        publish_state,
        write_lowcmd,
        robot: str = "caster",
        watchdog: float = 0.1,
        damping_kd: float = 1.0,
        state_every: int = 1,
        remote: drive.Remote | None = None,
        publish_operator=None,
        remote_rate: float = 20.0,
    ):
        self.sdk = sdk
        self.map = unitree.MotorMap.for_robot(robot)
        self.n = len(self.map)
        self.publish_state = publish_state
        self.write_lowcmd = write_lowcmd
        self.watchdog = watchdog
        self.damping_kd = damping_kd
        self.state_every = max(1, int(state_every))
        self._lock = threading.Lock()
        self._q = np.zeros(self.n)
        self.inbox = robot_side.CommandInbox(self.n)
        self.state_sender = P.Sender()
        self.lowcmd = sdk.new_lowcmd()
        self.mode = P.CommandMode.NONE
        self.mode_changes: list[tuple[float, P.CommandMode, str]] = [(time.monotonic(), self.mode, "")]
        self.bad_lowstates = 0
        self.lowstates = 0
        self.lowcmds_written = 0
        self.last_written: tuple[np.ndarray, ...] | None = None
        self.written_mode = P.CommandMode.NONE
        self.first_writes: list[tuple[float, P.CommandMode, str, float]] = []
        """(time the write returned, mode, why, arrival of the newest command) of the first
        LowCmd of each new mode: what left for the robot, and when."""
        self._running = False
        self._thread: threading.Thread | None = None
        # the Go2 remote (None: not used)
        self.remote = remote
        self.publish_operator = publish_operator
        self.remote_period = 1.0 / remote_rate
        self.operator_sender = P.Sender()
        self.operator_sent = 0
        self.operator_errors = 0
        self.bad_remote = 0
        self._remote_at = -math.inf
        self._remote_resume_at: float | None = None
        """Set by the remote's reset: damping goes on until a STANDUP command newer than it."""
        self._next_operator = -math.inf
        self._operator_active = False

    # --- the Go2 remote -----------------------------------------------------------------
    def on_remote(self, raw, now: float) -> None:
        """LowState.wireless_remote (40 bytes) -> the remote's decision; a stop is acted on
        by the next tick, whatever the bridge does."""
        try:
            state = drive.RemoteState.decode(raw)
        except ValueError:
            with self._lock:
                self.bad_remote += 1
            return
        with self._lock:
            was = self.remote.stopped
            self.remote.update(state)
            if state.present:
                self._remote_at = now
            if self.remote.stopped != was:
                self._next_operator = -math.inf  # tell the bridge at once
                self._remote_resume_at = None if self.remote.stopped else now

    def remote_damping(self, cmd, arrival: float) -> str:
        """Why the remote holds the robot in damping now ('' when it does not)."""
        with self._lock:
            if self.remote.stopped:
                return REMOTE_STOP_WHY
            if self._remote_resume_at is None:
                return ""
            if cmd is not None and cmd.mode == P.CommandMode.STANDUP and arrival >= self._remote_resume_at:
                self._remote_resume_at = None
                return ""
            return REMOTE_RESUME_WHY

    def _operator_tick(self, now: float) -> None:
        """Publish the remote's operator command every remote period while the remote
        reports (at once on a stop or a reset); one zero command when it stops reporting."""
        with self._lock:
            fresh = now - self._remote_at <= REMOTE_FRESH
            if fresh and now < self._next_operator:
                return
            if not fresh and not self._operator_active:
                return
            r = self.remote
            d = r.drive() if fresh else drive.Drive(propulsion=r.propulsion, stop=r.stopped)
            self._operator_active = fresh
            self._next_operator = now + self.remote_period
        self.publish_operator(d.command(self.operator_sender.next_header()).encode())
        self.operator_sent += 1

    # --- robot -> bridge --------------------------------------------------------------
    def on_lowstate(self, low) -> None:
        if self.remote is not None:  # first: a stop counts even in a LowState dropped below
            self.on_remote(low.wireless_remote, time.monotonic())
        quat, gyro, q, dq = self.map.read_state(low)
        with self._lock:
            self.lowstates += 1
            count = self.lowstates
        if not all(np.isfinite(v).all() for v in (quat, gyro, q, dq)) or abs(np.linalg.norm(quat) - 1.0) > 0.05:
            with self._lock:
                self.bad_lowstates += 1
            return
        with self._lock:
            self._q = q
        if count % self.state_every:
            return
        h = self.state_sender.next_header()
        self.inbox.round_trip.sent(h.seq, time.monotonic())
        msg = P.RobotState(
            quat=quat.tolist(), gyro=gyro.tolist(), q=q.tolist(), dq=dq.tolist(), robot_mode=self.mode, header=h
        )
        self.publish_state(msg.encode())

    # --- bridge -> robot --------------------------------------------------------------
    def targets(self, now: float) -> tuple[P.CommandMode, str, tuple[np.ndarray, ...] | None]:
        """(mode, reason, (q, dq, kp, kd)) to write now; None: write nothing."""
        cmd, arrival = self.inbox.latest()
        with self._lock:
            q_meas = self._q
        if self.remote is not None:
            why = self.remote_damping(cmd, arrival)
            if why:  # also before any command: a stop stops
                zeros = np.zeros(self.n)
                return P.CommandMode.DAMPING, why, (q_meas, zeros, zeros, np.full(self.n, self.damping_kd))
        if cmd is None:
            return P.CommandMode.NONE, "", None
        mode, why, *t = robot_side.command_targets(cmd, arrival, now, self.watchdog, self.damping_kd, q_meas)
        return mode, why, tuple(t)

    def tick(self, now: float) -> None:
        mode, why, t = self.targets(now)
        if mode != self.mode:
            self.mode = mode
            self.mode_changes.append((now, mode, why))
        if t is None:
            self._remote_tick(now)
            return
        # the same targets as the last LowCmd (between two commands, 9 of 10 ticks at 500 Hz):
        # the filled LowCmd and its CRC are written again as they are
        if self.last_written is None or not all(map(np.array_equal, t, self.last_written)):
            self.map.write_command(self.lowcmd, *t)
            self.last_written = t
        if self.write_lowcmd is not None:
            self.write_lowcmd(self.lowcmd)
        self.lowcmds_written += 1
        if mode != self.written_mode:
            self.written_mode = mode
            self.first_writes.append((time.monotonic(), mode, why, self.inbox.latest()[1]))
        self._remote_tick(now)

    def watchdog_delays(self) -> list[float]:
        """For each time the watchdog fired: seconds from the last command's arrival to the
        return of the first damping LowCmd's write."""
        return [t - arrival for t, _, why, arrival in self.first_writes if why == robot_side.WATCHDOG_WHY]

    def _remote_tick(self, now: float) -> None:
        """After the LowCmd: the remote's operator command, if one is due. A failing publish
        (the link gone) is counted and never stops the LowCmd loop."""
        if self.remote is None or self.publish_operator is None:
            return
        try:
            self._operator_tick(now)
        except Exception:  # noqa: BLE001 - the robot's loop must go on whatever zenoh does
            self.operator_errors += 1

    def _loop(self, rate: float) -> None:
        robot_side.run_fixed_rate(1.0 / rate, lambda: self._running, lambda now, _: self.tick(now))

    def start(self, rate: float) -> Go2Adapter:
        self._running = True
        self._thread = threading.Thread(target=self._loop, args=(rate,), name="go2-lowcmd", daemon=True)
        self._thread.start()
        return self

    def stop(self) -> None:
        self._running = False
        if self._thread is not None:
            self._thread.join(timeout=2.0)


def check_interface(interface: str, real_robot: bool, dry_run: bool) -> str | None:
    """The refusal message, or None when the adapter may start."""
    if interface in LOOPBACK or real_robot or dry_run:
        return None
    return (
        f"--network-interface {interface} is a real network: add --real-robot to command the robot on it "
        "(its sport mode must be off), or --dry-run to only forward states and log the commands"
    )


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(
        prog="go2_adapter", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    p.add_argument(
        "--robot",
        choices=go2.FOOT_KINDS,
        default="caster",
        help="joint set: caster / point (12 legs), wheel (Go2-W: 12 legs + 4 wheels)",
    )
    p.add_argument("--network-interface", default="lo", help="the robot's network, e.g. eth0 (default: lo)")
    p.add_argument("--domain-id", type=int, default=0, help="DDS domain (default: 0, the Go2's)")
    p.add_argument("--real-robot", action="store_true", help="allow a non-loopback interface: commands the robot")
    p.add_argument("--dry-run", action="store_true", help="never write rt/lowcmd; log what would be sent")
    p.add_argument("--cmd-rate", type=float, default=500.0, help="LowCmd messages per second (default: 500)")
    p.add_argument("--state-every", type=int, default=1, help="forward every N-th LowState (default: 1, all)")
    p.add_argument("--watchdog-ms", type=float, default=100.0, help="damp after this long without a command")
    p.add_argument("--damping-kd", type=float, default=1.0)
    p.add_argument("--duration", type=float, default=0.0, help="seconds (0: until Ctrl-C)")
    p.add_argument("--summary-every", type=float, default=10.0, help="seconds between status lines (0: none)")
    p.add_argument(
        "--remote",
        action="store_true",
        help="drive with the Go2's own remote (needs --policy or --task); its stop damps here, bridge or not",
    )
    p.add_argument("--remote-rate", type=float, default=20.0, help="operator commands per second from the remote")
    drive.add_drive_args(p)
    transport.add_zenoh_args(p, role="robot")
    args = p.parse_args(argv)
    refusal = check_interface(args.network_interface, args.real_robot, args.dry_run)
    if refusal:
        print(f"go2_adapter: error: {refusal}", file=sys.stderr)
        return 2
    if not (args.cmd_rate > 0 and math.isfinite(args.cmd_rate)):
        print("go2_adapter: error: --cmd-rate must be a positive number of messages per second", file=sys.stderr)
        return 2
    remote = None
    if args.remote:
        if not (args.policy or args.task):
            print("go2_adapter: error: --remote needs --policy DIR or --task NAME (its ranges)", file=sys.stderr)
            return 2
        if getattr(args, "secure", None):
            print(
                "go2_adapter: error: --remote with --secure: the robot's certificate may not put operator commands "
                "(only the operator's may), so the bridge would drop the remote's; drive with teleop instead",
                file=sys.stderr,
            )
            return 2
        if not (args.remote_rate > 0 and math.isfinite(args.remote_rate)):
            print("go2_adapter: error: --remote-rate must be a positive number per second", file=sys.stderr)
            return 2
        try:
            ranges, modes, source = drive.drive_limits(args)
        except ValueError as err:
            print(f"go2_adapter: error: {err}", file=sys.stderr)
            return 2
        remote = drive.Remote(ranges, zone=args.dead_zone, modes=modes, propulsion=modes[0])
    try:
        transport.check_options(args)  # endpoints and --secure's files, before the SDK starts
        sdk = unitree.load_sdk()
        session = transport.open_session(args)
    except (unitree.SdkUnavailable, transport.SessionError) as err:
        print(f"go2_adapter: error: {err}", file=sys.stderr)
        return 2
    keys = P.keys(args.namespace)
    state_pub = transport.fast_publisher(session, keys["state"])
    sdk.ChannelFactoryInitialize(args.domain_id, args.network_interface)
    writer = None
    if not args.dry_run:
        lowcmd_pub = sdk.ChannelPublisher(unitree.LOWCMD_TOPIC, sdk.LowCmd)
        lowcmd_pub.Init()
        writer = lowcmd_pub.Write
    a = Go2Adapter(
        sdk,
        state_pub.put,
        writer,
        robot=args.robot,
        watchdog=args.watchdog_ms / 1e3,
        damping_kd=args.damping_kd,
        state_every=args.state_every,
        remote=remote,
        publish_operator=session.declare_publisher(keys["operator"]).put if remote is not None else None,
        remote_rate=args.remote_rate,
    )
    cmd_sub = session.declare_subscriber(keys["cmd"], lambda s: a.on_command(s.payload.to_bytes()))
    low_sub = sdk.ChannelSubscriber(unitree.LOWSTATE_TOPIC, sdk.LowState)
    low_sub.Init(a.on_lowstate, 10)
    a.start(args.cmd_rate)
    what = "DRY RUN: rt/lowcmd is never written" if args.dry_run else f"rt/lowcmd at {args.cmd_rate:.0f} Hz"
    print(
        f"go2_adapter: {args.robot}, DDS domain {args.domain_id} on {args.network_interface}, zenoh namespace "
        f"{args.namespace}; {what}",
        flush=True,
    )
    print(f"go2_adapter: joint -> Unitree motor: {a.map.describe()}", flush=True)
    if remote is not None:
        print(
            f"go2_adapter: the Go2 remote drives on {keys['operator']} (ranges of {source}: {ranges.describe()}); "
            f"{remote.mapping.describe()}",
            flush=True,
        )
    watch, rates = robot_side.Watch("go2_adapter", a.mode_changes), robot_side.Rates()
    waited = False

    def tick(elapsed: float) -> None:
        nonlocal waited
        if not waited and a.lowstates == 0 and elapsed > 5.0:
            waited = True
            print(
                f"go2_adapter: no LowState in 5 s on {args.network_interface}, domain {args.domain_id}: is the "
                "robot on and connected to this interface?",
                flush=True,
            )

    def summary(seconds: float) -> None:
        low, cmds, written = rates(seconds, a.lowstates, a.commands_received, a.lowcmds_written)
        rejected = {k: v for k, v in a.rejected.items() if v}
        line = (
            f"go2_adapter: {a.mode.name}, LowState {low:.0f}/s, commands {cmds:.1f}/s, "
            f"LowCmd {written:.0f}/s{' (dry run, not sent)' if args.dry_run else ''}, "
            f"{a.inbox.round_trip.summary()}, bad LowState {a.bad_lowstates}, rejected {rejected or 'none'}"
        )
        if delays := a.watchdog_delays():
            line += f"; watchdog damping written {1e3 * delays[-1]:.1f} ms after the last command"
        if remote is not None:
            line += f"; remote: {a.operator_sent} operator commands sent ({a.operator_errors} failed)"
            line += f", stopped ({'+'.join(remote.mapping.reset)} resets)" if remote.stopped else ""
        if args.dry_run and a.last_written is not None:
            q, _, kp, kd = a.last_written
            line += f"; would send q {np.round(q, 2).tolist()} kp {kp.max():.0f} kd {kd.max():.1f}"
        print(line, flush=True)

    def close() -> None:
        a.stop()
        cmd_sub.undeclare()
        low_sub.Close()
        session.close()

    watch.serve(args.duration, args.summary_every, summary, close, tick)
    print(
        f"go2_adapter: LowState {a.lowstates} (bad {a.bad_lowstates}), commands {a.commands_received}, "
        f"LowCmd {a.lowcmds_written}{' (dry run)' if args.dry_run else ''}, rejected {a.rejected}, "
        f"mode {a.mode.name}"
        + "".join(f"; watchdog damping written {1e3 * d:.1f} ms after the last command" for d in a.watchdog_delays()),
        flush=True,
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
