"""A minimal operator: publish OperatorCommands to the bridge from the command line.

    python -m legged_casters.deploy.teleop --connect tcp/127.0.0.1:7447 --vx 0.3 --duration 5
    python -m legged_casters.deploy.teleop --connect tcp/127.0.0.1:7447 --propulsion front_wheel --vx 0.3
    python -m legged_casters.deploy.teleop --connect tcp/127.0.0.1:7447 --stop
    python -m legged_casters.deploy.teleop --connect tcp/127.0.0.1:7447 --reset

Velocity commands are repeated at ``--rate`` Hz for ``--duration`` seconds (the bridge
zeroes the command after its operator timeout, 1 s by default), then a zero command
is sent. ``--stop`` / ``--reset`` are sent a few times (the same flag each time, new
sequence numbers) so that one lost sample does not matter.
"""

from __future__ import annotations

import argparse
import contextlib
import sys
import time

from legged_casters.deploy import protocol as P
from legged_casters.deploy import transport


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--vx", type=float, default=0.0)
    p.add_argument("--vy", type=float, default=0.0)
    p.add_argument("--wz", type=float, default=0.0)
    p.add_argument("--propulsion", choices=[m.key for m in P.PropulsionMode], default="four_wheel")
    g = p.add_mutually_exclusive_group()
    g.add_argument("--stop", action="store_true", help="latch the bridge in damping")
    g.add_argument("--reset", action="store_true", help="release a stop or fault (the robot stands up again)")
    p.add_argument("--duration", type=float, default=1.0, help="seconds to repeat a velocity command")
    p.add_argument("--rate", type=float, default=10.0)
    transport.add_zenoh_args(p, role="operator")
    args = p.parse_args(argv)
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
        if args.stop or args.reset:
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
        status_sub.undeclare()
        pub.undeclare()
        session.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
