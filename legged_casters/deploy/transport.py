"""Zenoh session set-up shared by the bridge, the simulated robot and the benchmark.

Defaults are for a robot on a known network: peer mode, multicast scouting off, only
the endpoints given on the command line. ``--zenoh-config FILE`` loads a zenoh json5
configuration first (TLS, access control, shared memory, ...); ``--mode``,
``--listen`` and ``--connect`` are applied on top of it when given, and multicast
scouting stays off unless ``--multicast-scouting`` is given.
"""

from __future__ import annotations

import argparse
import json
import os
import re
from pathlib import Path

import zenoh

MODES = ("peer", "client")
ENDPOINT_RE = re.compile(r"^[a-z][a-z0-9-]*/\S+$")
"""<protocol>/<address>, e.g. tcp/127.0.0.1:7447 (zenoh's endpoint form, without metadata)."""


class SessionError(RuntimeError):
    """Zenoh could not start as asked: the message says in one line what to change."""


def check_endpoints(flag: str, endpoints: list[str]) -> None:
    for ep in endpoints:
        if not ENDPOINT_RE.match(ep.split("?")[0].split("#")[0]):
            hint = f"tcp/{ep}" if re.match(r"^[\w.\-\[\]:]+:\d+$", ep) else "tcp/HOST:PORT"
            raise SessionError(f"{flag} {ep!r} is not a zenoh endpoint: write it as <protocol>/<address>, e.g. {hint}")


def _first_line(err: Exception) -> str:
    text = str(err).strip().splitlines()[0] if str(err).strip() else type(err).__name__
    return re.sub(r"\s+at /\S+", "", text)  # zenoh appends source locations


def add_zenoh_args(parser: argparse.ArgumentParser) -> None:
    g = parser.add_argument_group("zenoh")
    g.add_argument("--mode", choices=MODES, default=None, help="zenoh mode (default: peer, or the config file's)")
    g.add_argument("--listen", action="append", default=[], help="endpoint to listen on, e.g. tcp/127.0.0.1:7447")
    g.add_argument("--connect", action="append", default=[], help="endpoint to connect to, e.g. tcp/127.0.0.1:7447")
    g.add_argument(
        "--multicast-scouting",
        action="store_true",
        help="enable multicast scouting (off by default: only explicit endpoints)",
    )
    g.add_argument("--zenoh-config", type=Path, default=None, help="zenoh json5 config file, applied first")
    g.add_argument("--namespace", default="go2", help="robot namespace: keys are <ns>/state, <ns>/cmd, ...")
    parser.add_argument(
        "--rt-priority",
        type=int,
        default=0,
        help="run the whole process under SCHED_FIFO with this priority (1-99; needs CAP_SYS_NICE; 0: off)",
    )


def make_config(
    mode: str | None = None,
    listen: list[str] | None = None,
    connect: list[str] | None = None,
    multicast_scouting: bool = False,
    config_file: str | Path | None = None,
) -> zenoh.Config:
    """A zenoh Config: the file (if any), then mode, endpoints and scouting on top."""
    if config_file is not None:
        path = Path(config_file)
        if not path.is_file():
            raise FileNotFoundError(f"zenoh config file {path} does not exist")
        cfg = zenoh.Config.from_file(str(path))
    else:
        cfg = zenoh.Config()
    if mode is not None or config_file is None:
        mode = mode or "peer"
        if mode not in MODES:
            raise ValueError(f"zenoh mode must be one of {MODES}, got {mode!r}")
        cfg.insert_json5("mode", json.dumps(mode))
    if listen:
        cfg.insert_json5("listen/endpoints", json.dumps(list(listen)))
    if connect:
        cfg.insert_json5("connect/endpoints", json.dumps(list(connect)))
    # off unless asked for on the command line, whatever the file says: a robot must not
    # discover (and start talking to) whatever else is on its network
    cfg.insert_json5("scouting/multicast/enabled", json.dumps(bool(multicast_scouting)))
    return cfg


def set_realtime(priority: int) -> bool:
    """Put the calling thread (and the threads it starts later, zenoh's included) under
    SCHED_FIFO. On a loaded machine this removes the multi-millisecond scheduling gaps
    that would otherwise trip the state watchdog. Returns False (with a warning) when
    the OS refuses."""
    if priority <= 0:
        return False
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))
        return True
    except (PermissionError, OSError, AttributeError) as e:
        print(f"warning: cannot set SCHED_FIFO priority {priority}: {e}; running with normal priority", flush=True)
        return False


def open_session(args: argparse.Namespace) -> zenoh.Session:
    """The session of a deploy tool; a mistyped endpoint, a port in use or a peer that
    does not answer (client mode) raise SessionError with the fix in one line."""
    set_realtime(getattr(args, "rt_priority", 0))
    check_endpoints("--listen", args.listen)
    check_endpoints("--connect", args.connect)
    try:
        config = make_config(args.mode, args.listen, args.connect, args.multicast_scouting, args.zenoh_config)
    except FileNotFoundError as err:
        raise SessionError(f"--zenoh-config: {err}") from None
    except zenoh.ZError as err:
        raise SessionError(f"zenoh rejected the configuration: {_first_line(err)}") from None
    try:
        return zenoh.open(config)
    except zenoh.ZError as err:
        text = str(err)
        if "Address already in use" in text:
            raise SessionError(
                f"--listen {', '.join(args.listen)}: the port is already in use (another bridge or sim_robot still "
                "running?); stop it or listen on another port"
            ) from None
        if "Unable to connect" in text:
            raise SessionError(
                f"--connect {', '.join(args.connect)}: nothing answered there; start the other side first "
                "(it must --listen on that address) or check the address"
            ) from None
        raise SessionError(f"zenoh could not start: {_first_line(err)}") from None


def fast_publisher(session: zenoh.Session, key: str) -> zenoh.Publisher:
    """A publisher for control traffic: real-time priority, no batching, drop when congested
    (a stale command is worse than a missing one; the watchdogs handle losses)."""
    return session.declare_publisher(
        key,
        priority=zenoh.Priority.REAL_TIME,
        express=True,
        congestion_control=zenoh.CongestionControl.DROP,
    )
