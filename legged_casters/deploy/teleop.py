"""A minimal operator: publish OperatorCommands to the bridge from the command line.

    python -m legged_casters.deploy.teleop --connect tcp/127.0.0.1:7447 --vx 0.3 --duration 5
    python -m legged_casters.deploy.teleop --connect tcp/127.0.0.1:7447 --propulsion front_wheel --vx 0.3
    python -m legged_casters.deploy.teleop --connect tcp/127.0.0.1:7447 --stop
    python -m legged_casters.deploy.teleop --connect tcp/127.0.0.1:7447 --reset

    python -m legged_casters.deploy.teleop --connect tcp/127.0.0.1:7447 --gamepad --policy exported/

Velocity commands are repeated at ``--rate`` Hz for ``--duration`` seconds (the bridge
zeroes the command after its operator timeout, 1 s by default), then a zero command
is sent. ``--stop`` / ``--reset`` are sent a few times (the same flag each time, new
sequence numbers) so that one lost sample does not matter.

``--gamepad [DEVICE]`` (default /dev/input/js0) drives from a gamepad instead, at
``--rate`` Hz until Ctrl-C (or ``--duration`` if given): sticks to vx / vy / wz with a
dead zone, scaled to and clamped inside the command ranges of ``--policy`` (the
export's training configuration) or ``--task`` (its defaults); released sticks send
exactly zero. A stop button latches the stop flag in every message until the reset
button; mode buttons pick the propulsion mode. If the gamepad cannot be read any more
(unplugged, a read error) one zero command is sent and sending stops, so the bridge's
operator timeout takes over. docs/driving.md has the button map.
"""

from __future__ import annotations

import argparse
import contextlib
import os
import sys
import time
from collections.abc import Callable

from legged_casters.deploy import drive, transport
from legged_casters.deploy import protocol as P

DEFAULT_GAMEPAD = "/dev/input/js0"


class GamepadLost(Exception):
    """The gamepad cannot be read any more (unplugged, a read error, end of its stream)."""


class JsDevice:
    """A joystick device (or any stream of js_event records: a pipe, a file) read without
    blocking."""

    def __init__(self, path: str):
        self.path = path
        self.fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK)
        self._rest = b""

    def read_events(self) -> list[drive.JsEvent]:
        """The events that arrived since the last call; raises GamepadLost."""
        events: list[drive.JsEvent] = []
        while True:
            try:
                data = os.read(self.fd, 64 * drive.JS_EVENT.size)
            except BlockingIOError:
                return events
            except OSError as err:  # ENODEV once unplugged
                raise GamepadLost(f"{self.path}: {err.strerror or err}") from None
            if not data:
                raise GamepadLost(f"{self.path}: end of the event stream")
            got, self._rest = drive.decode_js_events(self._rest + data)
            events += got

    def close(self) -> None:
        with contextlib.suppress(OSError):
            os.close(self.fd)


def drive_gamepad(
    read_events: Callable[[], list[drive.JsEvent]],
    pad: drive.Gamepad,
    send: Callable[[drive.Drive], None],
    rate: float,
    duration: float = 0.0,
    clock: Callable[[], float] = time.monotonic,
    sleep: Callable[[float], None] = time.sleep,
) -> str:
    """Send the gamepad's decision every 1/rate s, at absolute deadlines, until `duration`
    (0: until interrupted; a zero command then ends it) or the gamepad is lost (one zero
    command, keeping a latched stop, then nothing more). Returns why it ended."""
    t0, k = clock(), 0
    while True:
        try:
            for ev in read_events():
                pad.apply(ev)
        except GamepadLost as err:
            send(drive.Drive(propulsion=pad.propulsion, stop=pad.latch.stopped))
            return f"gamepad lost ({err}): sent a zero command and stopped sending"
        send(pad.drive())
        k += 1
        if duration > 0 and clock() - t0 >= duration:
            send(drive.Drive(propulsion=pad.propulsion, stop=pad.latch.stopped))
            return "duration over"
        sleep(max(0.0, t0 + k / rate - clock()))


class BridgeListens:
    """Whether the bridge takes this sender's messages, from its status: over each `every`
    seconds its count of accepted operator messages should grow by about what was sent,
    and its last accepted seq be one of ours. The bridge follows one operator sender at a
    time (docs/deploy.md, "Validation"), so another operator can take it over; then
    this one's stop does not reach it. Returns a line to print when the answer changes."""

    def __init__(self, statuses: list, every: float = 1.0):
        self.statuses, self.every = statuses, every
        self._at: tuple[float, int, int, int] | None = None  # (time, sent, our seq, accepted)
        self.ok: bool | None = None

    def __call__(self, now: float, sent: int, seq: int) -> str | None:
        if not self.statuses:
            return None
        accepted = self.statuses[-1].received_operator
        if self._at is None:
            self._at = (now, sent, seq, accepted)
            return None
        t, sent0, seq0, accepted0 = self._at
        if now - t < self.every:
            return None
        self._at = (now, sent, seq, accepted)
        d_sent, d_accepted = sent - sent0, accepted - accepted0
        ok = abs(d_accepted - d_sent) <= 3 + 0.3 * d_sent and seq0 - 3 <= self.statuses[-1].last_operator_seq <= seq
        if ok == self.ok or (self.ok is None and ok):
            self.ok = ok
            return None
        self.ok = ok
        if ok:
            return "teleop: the bridge takes this gamepad's messages again"
        return (
            f"teleop: WARNING: the bridge accepted {d_accepted} operator messages while this gamepad sent {d_sent}: "
            "another operator (a second teleop, go2_adapter --remote) is driving it, and this gamepad's stop "
            "does not reach it"
        )


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--vx", type=float, default=0.0)
    p.add_argument("--vy", type=float, default=0.0)
    p.add_argument("--wz", type=float, default=0.0)
    p.add_argument("--propulsion", choices=[m.key for m in P.PropulsionMode], default="four_wheel")
    g = p.add_mutually_exclusive_group()
    g.add_argument("--stop", action="store_true", help="latch the bridge in damping")
    g.add_argument("--reset", action="store_true", help="release a stop or fault (the robot stands up again)")
    g.add_argument(
        "--gamepad",
        nargs="?",
        const=DEFAULT_GAMEPAD,
        metavar="DEVICE",
        help=f"drive from a gamepad (default device {DEFAULT_GAMEPAD}); needs --policy or --task",
    )
    p.add_argument(
        "--duration",
        type=float,
        default=None,
        help="seconds to repeat a velocity command (default 1); with --gamepad: 0, until Ctrl-C",
    )
    p.add_argument("--rate", type=float, default=10.0)
    drive.add_drive_args(p)
    transport.add_zenoh_args(p, role="operator")
    args = p.parse_args(argv)
    if args.duration is None:
        args.duration = 0.0 if args.gamepad else 1.0
    pad = device = None
    if args.gamepad:
        if not (args.policy or args.task):
            p.error("--gamepad needs --policy DIR or --task NAME: they bound what the sticks command")
        if not args.rate > 0:
            p.error("--rate must be positive")
        try:
            ranges, modes, source = drive.drive_limits(args)
            device = JsDevice(args.gamepad)
        except ValueError as err:
            print(f"teleop: error: {err}", file=sys.stderr)
            return 2
        except OSError as err:
            print(f"teleop: error: cannot open the gamepad {args.gamepad}: {err.strerror or err}", file=sys.stderr)
            return 2
        prop0 = P.PropulsionMode[args.propulsion.upper()]
        pad = drive.Gamepad(ranges, zone=args.dead_zone, modes=modes, propulsion=prop0 if prop0 in modes else modes[0])
        print(f"teleop: gamepad {args.gamepad}; ranges of {source}: {ranges.describe()}", flush=True)
        print(f"teleop: {pad.mapping.describe()}", flush=True)
    try:
        session = transport.open_session(args)
    except transport.SessionError as err:
        print(f"teleop: error: {err}", file=sys.stderr)
        return 2
    keys = P.keys(args.namespace)
    pub = session.declare_publisher(keys["operator"])
    sender = P.Sender()
    statuses: list[P.BridgeStatus] = []

    def on_status(sample) -> None:
        with contextlib.suppress(P.ProtocolError):
            statuses.append(P.BridgeStatus.decode(sample.payload.to_bytes()))

    status_sub = session.declare_subscriber(keys["status"], on_status)
    sent = [0]
    prop = P.PropulsionMode[args.propulsion.upper()]

    def send(vx: float, vy: float, wz: float, flags: int = 0) -> None:
        pub.put(P.OperatorCommand(vx, vy, wz, prop, flags, sender.next_header()).encode())
        sent[0] += 1

    try:
        transport.arm_signals()
        time.sleep(0.5)  # let the session connect before the first sample
        if pad is not None:
            listens = BridgeListens(statuses)

            def send_drive(d: drive.Drive) -> None:
                h = sender.next_header()
                pub.put(d.command(h).encode())
                sent[0] += 1
                line = listens(time.monotonic(), sent[0], h.seq)
                if line:
                    print(line, flush=True)

            try:
                why = drive_gamepad(device.read_events, pad, send_drive, args.rate, args.duration)
            except KeyboardInterrupt:
                send_drive(drive.Drive(propulsion=pad.propulsion, stop=pad.latch.stopped))
                why = "interrupted: sent a zero command"
            print(f"teleop: {why}", flush=True)
        elif args.stop or args.reset:
            flags = P.OP_STOP if args.stop else P.OP_RESET
            for _ in range(3):
                send(0.0, 0.0, 0.0, flags)
                time.sleep(0.05)
        else:
            t0 = time.monotonic()
            k = 0
            while time.monotonic() - t0 < args.duration:
                send(args.vx, args.vy, args.wz)
                k += 1
                time.sleep(max(0.0, t0 + k / args.rate - time.monotonic()))
            send(0.0, 0.0, 0.0)
        time.sleep(0.3)  # a bridge publishes its status every 0.1 s
        first = next((st.received_operator for st in statuses), None)
        if statuses:
            st = statuses[-1]
            got = st.received_operator - (first or 0)
            print(
                f"teleop: sent {sent[0]} messages; the bridge on {keys['status']} accepted {got} of them while "
                f"listened to (total {st.received_operator}), it is {P.BridgeState(st.state).name}"
                + (f" ({P.Fault(st.fault).name})" if st.fault else ""),
                flush=True,
            )
        else:
            print(
                f"teleop: sent {sent[0]} messages but heard no bridge status on {keys['status']}: nobody is known to "
                "have received them (is the bridge running, with this --namespace and a matching --connect/--listen?)",
                flush=True,
            )
    except KeyboardInterrupt:
        pass
    finally:
        if device is not None:
            device.close()
        status_sub.undeclare()
        pub.undeclare()
        session.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
