"""A fake Go2 for tests: the MuJoCo robot of `sim_robot` behind Unitree's low-level DDS
topics, on the loopback interface only.

    python -m legged_casters.deploy.fake_go2 --domain-id 7 --listen tcp/127.0.0.1:7447

It publishes ``rt/lowstate`` (unitree_sdk2's ``LowState_``: IMU quaternion and gyro,
motor q / dq in Unitree's motor order, a millisecond ``tick``) at ``--state-rate`` and
consumes ``rt/lowcmd`` (``LowCmd_``) the way we understand the robot to: a command
whose CRC does not match is ignored; a motor slot in servo mode (0x01) applies
``tau = kp (q - q_meas) + kd (dq - dq_meas)`` in the physics loop, clipped to the torque
limits; a slot that is off applies nothing. Physics, start-up (``--startup``) and the
motor-side watchdog (damping after ``--watchdog-ms`` without a valid LowCmd) are
`sim_robot`'s. Whether a real Go2 damps, holds or goes limp when LowCmd stops is not
known here: the adapter never relies on it.

Its LowState's ``wireless_remote`` holds 40 zero bytes (no remote) until a test sets
what the Go2's remote would report with `FakeGo2.set_wireless_remote`.

With zenoh endpoints (``--listen`` / ``--connect``) it also publishes ``<ns>/sim/truth``
(trunk position and velocity, at most TRUTH_RATE_HZ) for tests; it never publishes our
state message: that is the adapter's job.
"""

from __future__ import annotations

import argparse
import sys
import time

import numpy as np

from legged_casters.deploy import protocol as P
from legged_casters.deploy import robot_side, transport, unitree
from legged_casters.deploy.sim_robot import SimRobot
from legged_casters.robot import go2

LOOPBACK = ("lo", "lo0")
TRUTH_RATE_HZ = 100.0
"""The most <ns>/sim/truth messages per second (every LowState's at 500 Hz cost a tenth of a
core in zenoh puts that only tests read)."""


class FakeGo2(SimRobot):
    def __init__(self, sdk: unitree.Sdk, publish_truth=None, **kwargs):
        super().__init__(self._publish, **kwargs)
        self.sdk = sdk
        self.map = unitree.MotorMap.for_robot(kwargs.get("robot", "caster"))
        self.publish_truth = publish_truth
        self.low = sdk.new_lowstate()
        self.low_pub = sdk.ChannelPublisher(unitree.LOWSTATE_TOPIC, sdk.LowState)
        self.low_pub.Init()
        self.cmd_sub = sdk.ChannelSubscriber(unitree.LOWCMD_TOPIC, sdk.LowCmd)
        self.cmd_sub.Init(self.on_lowcmd, 10)
        self.bad_crc = 0
        self.lowstates = 0
        self.cmd_sender = P.Sender()
        self.truth_every = max(1, round(1.0 / (self.dt * self.decimation * TRUTH_RATE_HZ)))
        self._remote = [0] * unitree.WIRELESS_REMOTE_SIZE
        self.remote_set_at: float | None = None
        """monotonic time of the last set_wireless_remote."""

    def set_wireless_remote(self, raw: bytes) -> None:
        """What the Go2's remote reports (40 bytes, drive.RemoteState.encode) from the next
        LowState on."""
        if len(raw) != unitree.WIRELESS_REMOTE_SIZE:
            raise ValueError(f"wireless_remote is {unitree.WIRELESS_REMOTE_SIZE} bytes, got {len(raw)}")
        self._remote = list(raw)
        self.remote_set_at = time.monotonic()

    def _publish(self, which: str, payload: bytes) -> None:
        if which == "truth" and self.publish_truth is not None:
            self.publish_truth(payload)

    def on_lowcmd(self, cmd) -> None:
        """DDS thread: a LowCmd -> the command the physics loop applies."""
        now = time.monotonic()
        if cmd.crc != unitree.lowcmd_crc(cmd) or tuple(cmd.head) != unitree.HEAD:
            self.bad_crc += 1  # only this (the DDS) thread writes it
            return
        servo, q, dq, kp, kd = self.map.read_command(cmd)
        if not all(np.isfinite(v).all() for v in (q[servo], dq[servo], kp, kd)):
            self.inbox.reject("nonfinite")
            return
        off = ~servo
        q, dq, kp, kd = np.where(off, 0.0, q), np.where(off, 0.0, dq), np.where(off, 0.0, kp), np.where(off, 0.0, kd)
        # LowCmd has no mode: all kp 0 is reported as damping (what the adapter sends for it)
        mode = P.CommandMode.DAMPING if not kp.any() else P.CommandMode.POLICY
        msg = P.JointCommand(
            mode=mode,
            q=q.tolist(),
            kp=kp.tolist(),
            kd=kd.tolist(),
            dq=dq.tolist(),
            header=self.cmd_sender.next_header(),
        )
        self.inbox.accept(msg, now)

    def _publish_state(self, stamp_ns: int) -> None:
        s = self.data.sensordata
        self.low.tick = int(self.data.time * 1000) & 0xFFFFFFFF
        self.map.write_state(self.low, s[self._quat], s[self._gyro], s[self._qs], s[self._dqs])
        self.low.wireless_remote = self._remote
        self.low_pub.Write(self.low)
        self.lowstates += 1
        if self.publish_truth is None or self.lowstates % self.truth_every:
            return
        h = self.truth_sender.next_header()
        h.stamp_ns = stamp_ns
        self._publish("truth", P.SimTruth(self.data.time, self.data.qpos[0:3], self.data.qvel[0:3], h).encode())


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(
        prog="fake_go2", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    p.add_argument("--robot", choices=go2.FOOT_KINDS, default="caster")
    p.add_argument("--domain-id", type=int, default=0, help="DDS domain (default: 0, the Go2's)")
    p.add_argument("--network-interface", default="lo", help="loopback only (default: lo)")
    p.add_argument("--state-rate", type=float, default=500.0, help="LowState messages per second (default: 500)")
    p.add_argument("--watchdog-ms", type=float, default=100.0, help="damp after this long without a LowCmd")
    p.add_argument("--damping-kd", type=float, default=1.0)
    p.add_argument(
        "--startup",
        choices=("hold", "damping"),
        default="hold",
        help="before the first LowCmd: hold the stand pose (default), or damp (the robot sinks to the "
        "floor; the bridge's default stand-up, --standup fold, gets it up from there: docs/deploy.md "
        "'Starting from the floor')",
    )
    p.add_argument("--duration", type=float, default=0.0, help="seconds (0: until Ctrl-C)")
    p.add_argument("--summary-every", type=float, default=10.0, help="seconds between status lines (0: none)")
    transport.add_zenoh_args(p, role="robot")
    args = p.parse_args(argv)
    if args.network_interface not in LOOPBACK:
        print(
            f"fake_go2: error: --network-interface {args.network_interface}: the fake robot runs on loopback only "
            "(lo), so that it can never talk to a real robot's network",
            file=sys.stderr,
        )
        return 2
    try:
        if args.listen or args.connect:
            transport.check_options(args)  # endpoints and --secure's files, before the SDK starts
        sdk = unitree.load_sdk()
    except (unitree.SdkUnavailable, transport.SessionError) as err:
        print(f"fake_go2: error: {err}", file=sys.stderr)
        return 2
    transport.stop_on_signals()  # also without a zenoh session (whose opening would install them)
    session, truth_pub = None, None
    if args.listen or args.connect:
        try:
            session = transport.open_session(args)
        except transport.SessionError as err:
            print(f"fake_go2: error: {err}", file=sys.stderr)
            return 2
        truth_pub = session.declare_publisher(P.keys(args.namespace)["truth"])
    sdk.ChannelFactoryInitialize(args.domain_id, args.network_interface)
    r = FakeGo2(
        sdk,
        publish_truth=truth_pub.put if truth_pub is not None else None,
        robot=args.robot,
        state_rate=args.state_rate,
        watchdog=args.watchdog_ms / 1e3,
        damping_kd=args.damping_kd,
        startup=args.startup,
    ).start()
    print(
        f"fake_go2: {args.robot} on DDS domain {args.domain_id} ({args.network_interface}), physics "
        f"{1 / r.dt:.0f} Hz, LowState {1 / (r.dt * r.decimation):.0f} Hz; motors {r.map.describe()}",
        flush=True,
    )
    watch, rates = robot_side.Watch("fake_go2", r.mode_changes), robot_side.Rates()

    def summary(seconds: float) -> None:
        (rate,) = rates(seconds, r.commands_received)
        print(
            f"fake_go2: {r.mode.name}, LowCmd {rate:.0f}/s, bad CRC {r.bad_crc}, sim time "
            f"{r.steps * r.dt:.1f} s, overruns {r.overruns}, trunk z {r.data.qpos[2]:.2f} m",
            flush=True,
        )

    def close() -> None:
        r.stop()
        if session is not None:
            session.close()

    watch.serve(args.duration, args.summary_every, summary, close)
    print(
        f"fake_go2: {r.steps} steps ({r.steps * r.dt:.1f} s), LowState {r.lowstates}, LowCmd {r.commands_received}, "
        f"bad CRC {r.bad_crc}, mode {r.mode.name}, trunk at ({r.data.qpos[0]:.3f}, {r.data.qpos[1]:.3f}, "
        f"{r.data.qpos[2]:.3f}) m",
        flush=True,
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
