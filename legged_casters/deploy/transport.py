"""Zenoh session set-up shared by the bridge, the simulated robot and the benchmark.

Defaults are for a robot on a known network: peer mode, multicast scouting off, only
the endpoints given on the command line. ``--zenoh-config FILE`` loads a zenoh json5
configuration first (shared memory, buffers, ...); ``--mode``, ``--listen`` and
``--connect`` are applied on top of it when given, and multicast scouting stays off
unless ``--multicast-scouting`` is given.

``--secure DIR`` (certificates from ``python -m legged_casters.deploy.certs DIR``)
secures the link: ``tls/`` endpoints only, mutual TLS with the tool's role certificate
(the bridge: bridge; sim_robot, fake_go2, go2_adapter: robot; teleop: operator), no
scouting, and zenoh access control that denies by default and lets each role's
certificate put only its own keys (:func:`access_control`).
"""

from __future__ import annotations

import argparse
import gc
import json
import os
import re
import shutil
import signal
import threading
from pathlib import Path

import zenoh

from legged_casters.deploy import certs
from legged_casters.deploy import protocol as P

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


def add_zenoh_args(parser: argparse.ArgumentParser, role: str | None = None) -> None:
    """The zenoh options of a deploy tool; ``role`` (one of :data:`certs.ROLES`) is the
    certificate the tool presents with ``--secure``."""
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
    if role is not None:
        g.add_argument(
            "--secure",
            type=Path,
            default=None,
            metavar="DIR",
            help=f"mutual TLS and access control with the certificates in DIR (ca.pem, {role}.pem, {role}.key; "
            "make them with: python -m legged_casters.deploy.certs DIR); endpoints must then be tls/HOST:PORT",
        )
        parser.set_defaults(secure_role=role)
    parser.add_argument(
        "--rt-priority",
        type=int,
        default=0,
        help="run the whole process under SCHED_FIFO with this priority (1-99; needs CAP_SYS_NICE; 0: off)",
    )


def access_control(namespace: str) -> dict:
    """zenoh's ``access_control`` configuration for a robot namespace, deny by default.

    Each node applies it to what arrives from the others (ingress), identifying them by
    the common name of their TLS certificate (``<role>.<ns>``, see :mod:`certs`):
    only the bridge may put ``<ns>/cmd`` and ``<ns>/status``, only the robot
    ``<ns>/state`` and ``<ns>/sim/truth``, only the operator ``<ns>/operator``. The three
    roles may declare subscribers on ``<ns>/**`` and are sent the namespace's samples
    (egress); nothing else is allowed, so a certificate of another namespace (or an
    unknown name) can neither send nor receive."""
    k = P.keys(namespace)
    ns = k["state"].rsplit("/", 1)[0]
    puts = {"robot": [k["state"], k["truth"]], "bridge": [k["cmd"], k["status"]], "operator": [k["operator"]]}
    rules = [
        {
            "id": f"{role}_puts",
            "messages": ["put"],
            "flows": ["ingress"],
            "permission": "allow",
            "key_exprs": keys,
        }
        for role, keys in puts.items()
    ]
    rules += [
        {
            "id": "subscribe",
            "messages": ["declare_subscriber"],
            "flows": ["ingress", "egress"],
            "permission": "allow",
            "key_exprs": [f"{ns}/**"],
        },
        {"id": "deliver", "messages": ["put"], "flows": ["egress"], "permission": "allow", "key_exprs": [f"{ns}/**"]},
    ]
    subjects = [{"id": role, "cert_common_names": [certs.common_name(role, namespace)]} for role in certs.ROLES]
    policies = [{"id": f"{role}_puts", "rules": [f"{role}_puts"], "subjects": [role]} for role in certs.ROLES]
    policies.append({"id": "members", "rules": ["subscribe", "deliver"], "subjects": list(certs.ROLES)})
    return {"enabled": True, "default_permission": "deny", "rules": rules, "subjects": subjects, "policies": policies}


def secure_settings(directory: str | Path, role: str, namespace: str) -> dict[str, object]:
    """The zenoh settings (path -> value) of a secured node: mutual TLS with the role's
    certificate from ``directory``, scouting off, :func:`access_control`. Raises
    SessionError naming the file and the fix when a file is missing or unusable
    (:func:`certs.check_material`: unreadable, empty, not PEM, a key that is not the
    certificate's, a certificate not signed by ``ca.pem`` or not a CA as ``ca.pem``,
    expired, for another role or namespace)."""
    d = Path(directory)
    make = f"python -m legged_casters.deploy.certs {d}"
    if role not in certs.ROLES:
        raise ValueError(f"role must be one of {certs.ROLES}, got {role!r}")
    files = {"ca": d / certs.CA_CERT, "cert": certs.cert_path(d, role), "key": certs.key_path(d, role)}
    missing = [str(f) for f in files.values() if not f.exists()]
    if missing:
        raise SessionError(
            f"--secure {d}: {', '.join(missing)} missing; make the certificates with `{make}` and copy ca.pem, "
            f"{role}.pem and {role}.key to this machine"
        )
    try:
        certs.check_material(d, role, namespace)
    except certs.MaterialError as err:
        raise SessionError(f"--secure {d}: {err}") from None
    tls = "transport/link/tls/"
    return {
        tls + "root_ca_certificate": str(files["ca"]),
        tls + "listen_certificate": str(files["cert"]),
        tls + "listen_private_key": str(files["key"]),
        tls + "connect_certificate": str(files["cert"]),
        tls + "connect_private_key": str(files["key"]),
        tls + "enable_mtls": True,
        # the peers are identified by the CA and their certificate's common name (access
        # control), not by the host name they are reached at, which need not be in the certificate
        tls + "verify_name_on_connect": False,
        tls + "close_link_on_expiration": True,
        "scouting/multicast/enabled": False,
        "scouting/gossip/enabled": False,
        "access_control": access_control(namespace),
    }


def check_secure_endpoints(flag: str, endpoints: list[str]) -> None:
    for ep in endpoints:
        if not ep.startswith("tls/"):
            rest = ep.split("/", 1)[1] if "/" in ep else ep
            raise SessionError(f"{flag} {ep!r}: with --secure every endpoint must be TLS: write tls/{rest}")


def make_config(
    mode: str | None = None,
    listen: list[str] | None = None,
    connect: list[str] | None = None,
    multicast_scouting: bool = False,
    config_file: str | Path | None = None,
    secure: dict[str, object] | None = None,
) -> zenoh.Config:
    """A zenoh Config: the file (if any), then mode, endpoints and scouting on top, then
    ``secure`` (:func:`secure_settings`) last."""
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
    if secure is not None:
        if multicast_scouting:
            raise SessionError("--multicast-scouting cannot be used with --secure: give the peers' tls/ endpoints")
        if not listen:
            # zenoh would otherwise listen on a plain tcp port of its choosing in peer mode
            cfg.insert_json5("listen/endpoints", "[]")
        for path, value in secure.items():
            cfg.insert_json5(path, json.dumps(value))
    return cfg


def normal_priority_cmd(cmd: list[str]) -> list[str]:
    """`cmd` started under the normal scheduler even from a SCHED_FIFO process (children
    inherit the policy; a deploy tool that imports and loads under SCHED_FIFO holds a core
    for a few hundred ms): through `chrt --other 0` where util-linux has it."""
    chrt = shutil.which("chrt")
    return [chrt, "--other", "0", *cmd] if chrt else list(cmd)


def set_realtime(priority: int) -> bool:
    """Put the calling thread (and the threads it starts later, zenoh's included) under
    SCHED_FIFO. Call it when the slow start-up work is done (imports, loading). On a
    loaded machine this removes the multi-millisecond scheduling gaps that would
    otherwise trip the state watchdog. Returns False (with a warning) when the OS refuses."""
    if priority <= 0:
        return False
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))
        return True
    except (PermissionError, OSError, AttributeError) as e:
        print(f"warning: cannot set SCHED_FIFO priority {priority}: {e}; running with normal priority", flush=True)
        return False


_signals = {"armed": False, "pending": False}


def _interrupt(signum, frame) -> None:
    if _signals["armed"]:
        raise KeyboardInterrupt
    _signals["pending"] = True  # between open_session and the tool's main loop: raised there


def stop_on_signals() -> None:
    """SIGTERM (systemd, `kill`) and SIGINT stop a deploy tool the way Ctrl-C does: its
    `finally` runs (sessions closed, the final summary printed). SIGINT too, because a
    shell starts background jobs with SIGINT ignored, and Python then never installs
    its Ctrl-C handler. A signal that arrives before the tool's main loop (`arm_signals`)
    is held until then: raised earlier it would skip the cleanup, and a zenoh session
    left open keeps the process alive. Only from the main thread."""
    if threading.current_thread() is not threading.main_thread():
        return
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, _interrupt)


def arm_signals() -> None:
    """Called first thing inside the `try` whose `finally` cleans up: from here a stop
    signal raises KeyboardInterrupt at once, and one that came before is raised now. It
    installs the handlers as well (`stop_on_signals`), so that a tool that opened no
    session (fake_go2 without --listen or --connect) stops cleanly too."""
    stop_on_signals()
    _signals["armed"] = True
    if _signals["pending"]:
        _signals["pending"] = False
        raise KeyboardInterrupt


def check_options(args: argparse.Namespace) -> None:
    """The zenoh options' checks that need no session: endpoints and, with ``--secure``,
    every certificate and key file (:func:`secure_settings`). A tool calls it first, so
    that a mistake stops it at once, before its slow start-up work; ``open_session``
    checks the same again. Raises SessionError."""
    check_endpoints("--listen", args.listen)
    check_endpoints("--connect", args.connect)
    if getattr(args, "secure", None) is not None:
        check_secure_endpoints("--listen", args.listen)
        check_secure_endpoints("--connect", args.connect)
        secure_settings(args.secure, args.secure_role, args.namespace)


def open_session(args: argparse.Namespace) -> zenoh.Session:
    """The session of a deploy tool; a mistyped endpoint, a port in use or a peer that
    does not answer (client mode) raise SessionError with the fix in one line. From here
    on SIGTERM and SIGINT stop the tool like Ctrl-C (`stop_on_signals`)."""
    stop_on_signals()
    # The objects made so far (modules, the policy) are never garbage: keep the collector
    # from walking them again at every full collection while the tool runs.
    gc.collect()
    gc.freeze()
    set_realtime(getattr(args, "rt_priority", 0))
    check_endpoints("--listen", args.listen)
    check_endpoints("--connect", args.connect)
    secure = None
    if getattr(args, "secure", None) is not None:
        check_secure_endpoints("--listen", args.listen)
        check_secure_endpoints("--connect", args.connect)
        secure = secure_settings(args.secure, args.secure_role, args.namespace)
    try:
        config = make_config(
            args.mode, args.listen, args.connect, args.multicast_scouting, args.zenoh_config, secure=secure
        )
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
