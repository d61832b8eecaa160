"""--secure: mutual TLS and access control over loopback.

Each refusal has a control beside it: the same attempt with the right certificate gets
through, so a test that passes is not passing because nothing would ever arrive.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import zenoh
from test_deploy import LOAD_STATE_AGE_MS, free_port, wait_for

from legged_casters.deploy import certs, transport
from legged_casters.deploy import protocol as P
from legged_casters.deploy.simple_policy import write_policy
from legged_casters.robot import go2

REPO = Path(__file__).resolve().parents[1]
NS = "t_sec"


@pytest.fixture(scope="module")
def pki(tmp_path_factory) -> dict[str, Path]:
    """ours: CA + all roles (via the CLI); foreign: another CA's; expired: our CA, a
    bridge certificate that expired yesterday; other_ns: our CA, roles of another namespace."""
    root = tmp_path_factory.mktemp("pki")
    ours = root / "ours"
    assert certs.main([str(ours), "--namespace", NS]) == 0
    certs.make_all(root / "foreign", namespace=NS)
    expired = root / "expired"
    certs.make_role_cert(certs.load_ca(ours), expired, "bridge", NS, days=1, backdate_days=2)
    shutil.copy(ours / certs.CA_CERT, expired / certs.CA_CERT)
    other = root / "other_ns"
    for role in certs.ROLES:
        certs.make_role_cert(certs.load_ca(ours), other, role, "t_other")
    shutil.copy(ours / certs.CA_CERT, other / certs.CA_CERT)
    return {"ours": ours, "foreign": root / "foreign", "expired": expired, "other_ns": other}


def tls_files(directory: Path, role: str | None) -> dict[str, object]:
    """TLS settings without --secure's own checks (expiry, name) and without access
    control: what a peer that does not play by our rules would configure."""
    tls = "transport/link/tls/"
    out: dict[str, object] = {
        tls + "root_ca_certificate": str(directory / certs.CA_CERT),
        tls + "verify_name_on_connect": False,
    }
    if role is not None:
        out.update({tls + "connect_certificate": str(certs.cert_path(directory, role))})
        out.update({tls + "connect_private_key": str(certs.key_path(directory, role))})
        out[tls + "enable_mtls"] = True
    return out


def secure_peer(directory: Path, role: str, listen: int | None = None, connect: int | None = None, ns: str = NS):
    return zenoh.open(
        transport.make_config(
            "peer",
            listen=[f"tls/127.0.0.1:{listen}"] if listen else None,
            connect=[f"tls/127.0.0.1:{connect}"] if connect else None,
            secure=transport.secure_settings(directory, role, ns),
        )
    )


def raw_peer(connect: str, settings: dict[str, object] | None) -> zenoh.Session:
    cfg = transport.make_config("peer", connect=[connect])
    for path, value in (settings or {}).items():
        cfg.insert_json5(path, json.dumps(value))
    return zenoh.open(cfg)


def _put_and_count(sender: zenoh.Session, key: str, received: list, n: int = 10) -> int:
    """Put n samples on key from sender (after its declarations have propagated); the
    number of them the receiver's subscriber got."""
    time.sleep(0.3)
    before = len(received)
    pub = sender.declare_publisher(key)
    for i in range(n):
        pub.put(b"x%d" % i)
        time.sleep(0.005)
    wait_for(lambda: len(received) - before >= n, 1.0)
    time.sleep(0.1)
    pub.undeclare()
    return len(received) - before


# --- configuration and start-up errors -----------------------------------------------------
def test_certs_cli_writes_a_ca_and_one_certificate_per_role(pki):
    d = pki["ours"]
    for role in certs.ROLES:
        cn, start, end = certs.describe(certs.cert_path(d, role))
        assert cn == f"{role}.{NS}" and (end - start).days >= 364
        assert certs.key_path(d, role).stat().st_mode & 0o077 == 0  # private keys: owner only
    assert certs.main([str(d), "--namespace", NS]) == 2  # no silent overwrite


def test_access_control_is_deny_by_default_and_generated_from_the_namespace():
    acl = transport.access_control("robot7")
    assert acl["enabled"] and acl["default_permission"] == "deny"
    puts = {r["id"]: r["key_exprs"] for r in acl["rules"] if r["messages"] == ["put"] and r["flows"] == ["ingress"]}
    assert puts == {
        "robot_puts": ["robot7/state", "robot7/sim/truth"],
        "bridge_puts": ["robot7/cmd", "robot7/status"],
        "operator_puts": ["robot7/operator"],
    }
    names = {s["id"]: s["cert_common_names"] for s in acl["subjects"]}
    assert names == {"robot": ["robot.robot7"], "bridge": ["bridge.robot7"], "operator": ["operator.robot7"]}


def _open_args(tool_role: str, *argv: str) -> argparse.Namespace:
    p = argparse.ArgumentParser()
    transport.add_zenoh_args(p, role=tool_role)
    return p.parse_args(list(argv))


@pytest.mark.parametrize(
    ("which", "argv", "message"),
    [
        ("missing", ["--listen", "tls/127.0.0.1:{port}"], "python -m legged_casters.deploy.certs"),
        ("ours", ["--listen", "tcp/127.0.0.1:{port}"], "write tls/127.0.0.1:"),
        ("ours", ["--listen", "tls/127.0.0.1:{port}", "--namespace", "elsewhere"], "--namespace elsewhere"),
        ("expired", ["--connect", "tls/127.0.0.1:{port}"], "expired on"),
        ("ours", ["--listen", "tls/127.0.0.1:{port}", "--multicast-scouting"], "cannot be used with --secure"),
    ],
)
def test_secure_start_up_errors_say_how_to_fix(pki, tmp_path, which, argv, message):
    d = tmp_path / "nothing" if which == "missing" else pki[which]
    argv = [a.format(port=free_port()) for a in argv]
    ns = [] if "--namespace" in argv else ["--namespace", NS]
    args = _open_args("bridge", "--secure", str(d), *argv, *ns)
    with pytest.raises(transport.SessionError) as err:
        transport.open_session(args).close()
    assert message in str(err.value), str(err.value)


def test_tool_cli_names_the_certs_command(tmp_path):
    out = subprocess.run(
        [sys.executable, "-m", "legged_casters.deploy.teleop", "--secure", str(tmp_path / "none"),
         "--connect", f"tls/127.0.0.1:{free_port()}", "--duration", "0.1"],
        cwd=REPO, env={**os.environ, "PYTHONPATH": str(REPO)}, capture_output=True, text=True, timeout=60,
    )  # fmt: skip
    assert out.returncode == 2 and "Traceback" not in out.stderr
    assert "operator.pem" in out.stderr and "python -m legged_casters.deploy.certs" in out.stderr, out.stderr


# --- broken certificate material -----------------------------------------------------------
def _encrypted(key_file: Path) -> bytes:
    from cryptography.hazmat.primitives import serialization as ser

    key = ser.load_pem_private_key(key_file.read_bytes(), password=None)
    return key.private_bytes(ser.Encoding.PEM, ser.PrivateFormat.PKCS8, ser.BestAvailableEncryption(b"secret"))


BROKEN = {  # case: (the file it breaks, what the one-line error says about it)
    "empty key": ("key", "is empty"),
    "garbage key": ("key", "holds no PEM private key"),
    "another certificate's key": ("key", "is not the key of"),
    "encrypted key": ("key", "is encrypted"),
    "key is a folder": ("key", "is a folder, not a file"),
    "empty ca.pem": ("ca", "is empty"),
    "garbage ca.pem": ("ca", "holds no PEM certificate"),
    "leaf certificate as ca.pem": ("ca", "is not a CA certificate"),
    "damaged certificate": ("cert", "is not a PEM certificate"),
    "certificate of another CA": ("cert", "is not signed by the CA"),
}


def broken_dir(pki: dict[str, Path], tmp: Path, role: str, case: str) -> tuple[Path, Path]:
    """A copy of our CA and role's files with one thing broken: (directory, broken file)."""
    d = tmp / "broken"
    d.mkdir(parents=True)
    ours = pki["ours"]
    ca, cert, key = d / certs.CA_CERT, certs.cert_path(d, role), certs.key_path(d, role)
    for f in (ca, cert, key):
        shutil.copy(ours / f.name, f)
    other = next(r for r in certs.ROLES if r != role)
    if case == "empty key":
        key.write_bytes(b"")
    elif case == "garbage key":
        key.write_bytes(b"\x00\x13 not a key at all\n")
    elif case == "another certificate's key":
        shutil.copy(certs.key_path(ours, other), key)
    elif case == "encrypted key":
        key.write_bytes(_encrypted(certs.key_path(ours, role)))
    elif case == "key is a folder":
        key.unlink()
        key.mkdir()
    elif case == "empty ca.pem":
        ca.write_bytes(b"")
    elif case == "garbage ca.pem":
        ca.write_bytes(b"ca\n")
    elif case == "leaf certificate as ca.pem":
        shutil.copy(certs.cert_path(ours, other), ca)
    elif case == "damaged certificate":
        text = cert.read_text().splitlines()
        cert.write_text("\n".join(text[:1] + ["AAAA" + line[4:] for line in text[1:-1]] + text[-1:]) + "\n")
    elif case == "certificate of another CA":
        shutil.copy(certs.cert_path(pki["foreign"], role), cert)
        shutil.copy(certs.key_path(pki["foreign"], role), key)
    else:
        raise ValueError(case)
    return d, {"ca": ca, "cert": cert, "key": key}[BROKEN[case][0]]


@pytest.mark.parametrize("case", list(BROKEN))
def test_broken_certificate_material_is_named_at_start(pki, tmp_path, case):
    """Every file is parsed and checked before a session opens: one line naming the file,
    what is wrong and the fix. Control: the same directory with the file intact passes."""
    for role in ("bridge", "robot"):
        d, bad = broken_dir(pki, tmp_path / role, role, case)
        args = _open_args(role, "--secure", str(d), "--connect", f"tls/127.0.0.1:{free_port()}", "--namespace", NS)
        with pytest.raises(transport.SessionError) as err:
            transport.check_options(args)
        msg = str(err.value)
        assert "\n" not in msg and f"{bad} {BROKEN[case][1]}" in msg, msg
        assert "python -m legged_casters.deploy.certs" in msg or "copy" in msg, msg
    ok = _open_args("bridge", "--secure", str(pki["ours"]), "--connect", "tls/127.0.0.1:1", "--namespace", NS)
    transport.check_options(ok)


@pytest.mark.parametrize(
    ("tool", "role", "case", "endpoint"),
    [
        ("bridge", "bridge", "another certificate's key", "--connect"),
        ("bridge", "bridge", "empty ca.pem", "--connect"),
        ("bridge", "bridge", "leaf certificate as ca.pem", "--listen"),
        ("bridge", "bridge", "key is a folder", "--listen"),
        ("sim_robot", "robot", "garbage key", "--listen"),
        ("go2_adapter", "robot", "certificate of another CA", "--connect"),
        ("teleop", "operator", "encrypted key", "--connect"),
    ],
)
def test_tools_exit_2_at_once_on_broken_certificate_material(pki, tmp_path, tool, role, case, endpoint):
    """The bridge with --connect (its documented role) or --listen, sim_robot, the Go2
    adapter and teleop: exit 2 at start with one line on stderr, not a wait until
    --duration or zenoh's own message."""
    d, bad = broken_dir(pki, tmp_path, role, case)
    extra = {"bridge": ["--summary-every", "0"], "go2_adapter": ["--network-interface", "lo"]}.get(tool, [])
    t0 = time.monotonic()
    out = subprocess.run(
        [sys.executable, "-m", f"legged_casters.deploy.{tool}", "--secure", str(d), "--namespace", NS,
         endpoint, f"tls/127.0.0.1:{free_port()}", "--duration", "30", *extra],
        cwd=REPO, env={**os.environ, "PYTHONPATH": str(REPO)}, capture_output=True, text=True, timeout=60,
    )  # fmt: skip
    elapsed = time.monotonic() - t0
    lines = out.stderr.strip().splitlines()
    assert out.returncode == 2 and len(lines) == 1, out.stderr
    assert lines[0].startswith(f"{tool}: error: --secure {d}: {bad} {BROKEN[case][1]}"), lines[0]
    assert elapsed < 10.0, elapsed  # about 0.5-1 s on a loaded 2-core machine, most of it Python's imports


# --- who may connect -----------------------------------------------------------------------
@pytest.mark.parametrize("case", ["plain_tcp", "tls_without_certificate", "foreign_ca", "expired", "valid"])
def test_only_a_current_certificate_of_our_ca_connects(pki, case):
    """A robot listens with --secure and publishes its state. Refused peers are never
    connected, receive none of the state and deliver no command; the valid control is
    connected, hears the state and delivers."""
    port = free_port()
    robot = secure_peer(pki["ours"], "robot", listen=port)
    cmds: list = []
    sub = robot.declare_subscriber(f"{NS}/cmd", lambda s: cmds.append(1))
    state_pub = robot.declare_publisher(f"{NS}/state")
    tls = f"tls/127.0.0.1:{port}"
    attempt = {
        "plain_tcp": lambda: raw_peer(f"tcp/127.0.0.1:{port}", None),
        "tls_without_certificate": lambda: raw_peer(tls, tls_files(pki["ours"], None)),
        # its own CA's bridge certificate; trusting our CA (so that only the client side is refused)
        "foreign_ca": lambda: raw_peer(
            tls,
            {
                **tls_files(pki["foreign"], "bridge"),
                "transport/link/tls/root_ca_certificate": str(pki["ours"] / "ca.pem"),
            },
        ),
        "expired": lambda: raw_peer(tls, tls_files(pki["expired"], "bridge")),
        "valid": lambda: raw_peer(tls, tls_files(pki["ours"], "bridge")),
    }[case]
    other = attempt()
    heard: list = []
    try:
        other_sub = other.declare_subscriber(f"{NS}/state", lambda s: heard.append(1))
        time.sleep(0.5)
        for _ in range(10):
            state_pub.put(b"state")
            time.sleep(0.005)
        delivered = _put_and_count(other, f"{NS}/cmd", cmds)
        connected = len(list(robot.info.peers_zid()))
        other_sub.undeclare()
    finally:
        other.close()
        sub.undeclare()
        robot.close()
    if case == "valid":
        assert connected == 1 and delivered == 10 and len(heard) == 10
    else:
        assert connected == 0 and delivered == 0 and heard == [], (connected, delivered, len(heard))


@pytest.mark.parametrize("listener_ca", ["foreign", "ours"])
def test_a_secured_peer_refuses_a_listener_of_another_ca(pki, listener_ca):
    """The other direction: a robot with --secure connects to a listener presenting a
    bridge certificate of another CA (refused) or of ours (the control: connected)."""
    port = free_port()
    tls = "transport/link/tls/"
    listener_cfg = transport.make_config("peer", listen=[f"tls/127.0.0.1:{port}"])
    files = {
        tls + "root_ca_certificate": str(pki["ours"] / certs.CA_CERT),  # it would accept our robot
        tls + "listen_certificate": str(certs.cert_path(pki[listener_ca], "bridge")),
        tls + "listen_private_key": str(certs.key_path(pki[listener_ca], "bridge")),
        tls + "enable_mtls": True,
    }
    for path, value in files.items():
        listener_cfg.insert_json5(path, json.dumps(value))
    listener = zenoh.open(listener_cfg)
    robot = secure_peer(pki["ours"], "robot", connect=port)
    try:
        connected = wait_for(lambda: len(list(listener.info.peers_zid())) == 1, 2.0)
    finally:
        robot.close()
        listener.close()
    assert connected == (listener_ca == "ours")


# --- who may put what ----------------------------------------------------------------------
@pytest.mark.parametrize(
    ("key", "receiver", "allowed"),
    [("cmd", "robot", "bridge"), ("state", "bridge", "robot"), ("operator", "bridge", "operator")],
)
def test_only_the_owning_role_may_put_a_key(pki, key, receiver, allowed):
    """The receiver (with --secure) subscribes to <ns>/<key>. Peers with valid certificates
    of our CA connect and put: only the owning role's samples arrive (the control);
    every other role's, and the owning role's certificate for another namespace, do not."""
    port = free_port()
    rx = secure_peer(pki["ours"], receiver, listen=port)
    got: list = []
    sub = rx.declare_subscriber(f"{NS}/{key}", lambda s: got.append(1))
    counts = {}
    try:
        senders = [(r, "ours", r) for r in certs.ROLES] + [(f"{allowed} of t_other", "other_ns", allowed)]
        for name, which, role in senders:
            # a peer that does not restrict itself: plain mTLS, no access control of its own
            s = raw_peer(f"tls/127.0.0.1:{port}", tls_files(pki[which], role))
            try:
                assert wait_for(lambda: len(list(rx.info.peers_zid())) == 1, 5.0), f"{name} did not connect"
                counts[name] = _put_and_count(s, f"{NS}/{key}", got)
            finally:
                s.close()
            assert wait_for(lambda: not list(rx.info.peers_zid()), 5.0)
    finally:
        sub.undeclare()
        rx.close()
    assert counts.pop(allowed) == 10, "control: the owning role's samples must arrive"
    assert all(n == 0 for n in counts.values()), counts


# --- the secured chain ---------------------------------------------------------------------
def _spawn(module: str, *args: str) -> subprocess.Popen:
    return subprocess.Popen(
        [sys.executable, "-m", f"legged_casters.deploy.{module}", *args],
        cwd=REPO,
        env={**os.environ, "PYTHONPATH": str(REPO)},
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )


def _stop(*procs: subprocess.Popen | None) -> str:
    out = ""
    for p in procs:
        if p is not None and p.poll() is None:
            p.send_signal(signal.SIGINT)
            try:
                p.wait(10)
            except subprocess.TimeoutExpired:
                p.kill()
        if p is not None and p.stdout is not None:
            out += p.stdout.read()
    return out


@pytest.mark.realtime
def test_secured_chain_runs_and_ignores_wrong_role_messages(pki, tmp_path):
    """bridge --listen, sim_robot --listen and --connect to the bridge, all with --secure:
    the bridge reaches RUNNING and policy commands reach the robot; teleop --secure is
    accepted. A peer with the operator's certificate puts damping commands to the robot
    and states to the bridge, one with the robot's certificate puts an operator stop: the
    robot keeps following the policy and the bridge keeps running with nothing rejected
    (nothing arrived). Then the real operator's stop (control) stops the bridge."""
    d = pki["ours"]
    policy = write_policy(tmp_path / "policy", crouch_gain=0.2).parent
    pb, pr = free_port(), free_port()
    sec = ["--secure", str(d), "--namespace", NS]
    bridge = _spawn(
        "bridge", "--policy", str(policy), "--listen", f"tls/127.0.0.1:{pb}", *sec,
        "--standup-time", "0.5", "--operator-timeout", "0", "--max-state-age-ms", LOAD_STATE_AGE_MS,
    )  # fmt: skip
    robot = _spawn(
        "sim_robot", "--listen", f"tls/127.0.0.1:{pr}", "--connect", f"tls/127.0.0.1:{pb}", *sec,
        "--watchdog-ms", "300", "--summary-every", "0",
    )  # fmt: skip
    # the probe: an operator (it may listen to everything in the namespace), on both
    probe = zenoh.open(
        transport.make_config(
            "peer",
            connect=[f"tls/127.0.0.1:{pb}", f"tls/127.0.0.1:{pr}"],
            secure=transport.secure_settings(d, "operator", NS),
        )
    )
    states: list[P.RobotState] = []
    cmds: list[P.JointCommand] = []
    statuses: list[P.BridgeStatus] = []
    subs = [
        probe.declare_subscriber(f"{NS}/state", lambda s: states.append(P.RobotState.decode(s.payload.to_bytes()))),
        probe.declare_subscriber(f"{NS}/cmd", lambda s: cmds.append(P.JointCommand.decode(s.payload.to_bytes()))),
        probe.declare_subscriber(
            f"{NS}/status", lambda s: statuses.append(P.BridgeStatus.decode(s.payload.to_bytes()))
        ),
    ]
    attackers: list[zenoh.Session] = []
    log = ""
    try:
        running = lambda: statuses and statuses[-1].state == P.BridgeState.RUNNING  # noqa: E731
        ok = wait_for(lambda: running() and any(c.mode == P.CommandMode.POLICY for c in cmds), 40.0)
        assert ok, "the secured bridge never ran the policy"
        assert wait_for(lambda: states and states[-1].robot_mode == P.CommandMode.POLICY, 5.0)

        teleop = subprocess.run(
            [sys.executable, "-m", "legged_casters.deploy.teleop", "--connect", f"tls/127.0.0.1:{pb}", *sec,
             "--vx", "0.2", "--duration", "0.5"],
            cwd=REPO, env={**os.environ, "PYTHONPATH": str(REPO)}, capture_output=True, text=True, timeout=60,
        )  # fmt: skip
        assert teleop.returncode == 0, teleop.stderr
        assert statuses[-1].received_operator > 0, teleop.stdout

        # wrong roles, valid certificates of our CA, no access control of their own
        op_cfg = tls_files(d, "operator")
        rob_cfg = tls_files(d, "robot")
        a_op = raw_peer(f"tls/127.0.0.1:{pr}", op_cfg)
        a_op_b = raw_peer(f"tls/127.0.0.1:{pb}", op_cfg)
        a_rob = raw_peer(f"tls/127.0.0.1:{pb}", rob_cfg)
        attackers += [a_op, a_op_b, a_rob]
        time.sleep(0.5)
        n_states, before = len(states), statuses[-1]
        damp = a_op.declare_publisher(f"{NS}/cmd")
        fake_state = a_op_b.declare_publisher(f"{NS}/state")
        stop = a_rob.declare_publisher(f"{NS}/operator")
        s_cmd, s_state, s_op = P.Sender(), P.Sender(), P.Sender()
        q0 = go2.default_joint_positions()
        for _ in range(25):
            damp.put(
                P.JointCommand(
                    P.CommandMode.DAMPING, [0.0] * 12, [0.0] * 12, [5.0] * 12, 0, s_cmd.next_header()
                ).encode()
            )
            h = s_state.next_header()
            fake_state.put(P.RobotState([1.0, 0.0, 0.0, 0.0], [0.0] * 3, list(q0), [0.0] * 12, header=h).encode())
            stop.put(
                P.OperatorCommand(0.0, 0.0, 0.0, P.PropulsionMode.FOUR_WHEEL, P.OP_STOP, s_op.next_header()).encode()
            )
            time.sleep(0.02)
        time.sleep(0.4)
        after = statuses[-1]
        assert all(s.robot_mode == P.CommandMode.POLICY for s in states[n_states:]), "the robot obeyed a wrong role"
        assert after.state == P.BridgeState.RUNNING, P.BridgeState(after.state).name
        assert after.received_operator == before.received_operator, "an operator message from the robot's certificate"
        assert sum(after.rejected) == sum(before.rejected) == 0
        # states: only the real robot's, one per period (the fake ones would add about 25)
        gained = after.received_state - before.received_state
        assert gained <= len(states) - n_states + 5, (gained, len(states) - n_states)

        # control: the operator's own stop does stop the bridge
        op_pub = a_op_b.declare_publisher(f"{NS}/operator")
        for _ in range(3):
            op_pub.put(
                P.OperatorCommand(0.0, 0.0, 0.0, P.PropulsionMode.FOUR_WHEEL, P.OP_STOP, s_op.next_header()).encode()
            )
            time.sleep(0.05)
        assert wait_for(lambda: statuses[-1].state == P.BridgeState.STOPPED, 2.0), "control: the operator's stop"
    finally:
        for a in attackers:
            a.close()
        for s in subs:
            s.undeclare()
        probe.close()
        log = _stop(bridge, robot)
    assert "Traceback" not in log, log
