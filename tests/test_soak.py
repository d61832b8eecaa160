"""scripts/soak.py in its short forms, and how the deploy tools stop: SIGINT and SIGTERM
end them cleanly even when a shell started them with SIGINT ignored."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from test_deploy import free_port

from legged_casters.deploy import transport

REPO = Path(__file__).resolve().parents[1]
ENV = {**os.environ, "PYTHONPATH": str(REPO)}


def _run_soak(out: Path, *args: str, timeout: float) -> subprocess.CompletedProcess:
    """scripts/soak.py with `args`, no load beside it, SCHED_FIFO 10 where allowed; it must exit 0."""
    cmd = [sys.executable, "scripts/soak.py", *args, "--load", "none", "--rt-priority", "10"]
    cmd += ["--port", str(free_port()), "--out", str(out)]
    res = subprocess.run(cmd, cwd=REPO, env=ENV, capture_output=True, text=True, timeout=timeout)
    assert res.returncode == 0, res.stdout[-3000:] + res.stderr[-3000:]
    return res


def signal_when_ready(cmd: list[str], ready: str, sig: int, settle: float = 0.0) -> tuple[int, str]:
    """Start `cmd` from a shell with SIGINT ignored (as a background job of a
    non-interactive shell starts), wait up to 60 s for a stdout line containing `ready`,
    `settle` s more, then send `sig`: (exit code, the rest of its stdout)."""
    shell = "trap '' INT; exec " + " ".join(cmd)  # the exec'd tool inherits SIGINT ignored
    proc = subprocess.Popen(["sh", "-c", shell], cwd=REPO, env=ENV, stdout=subprocess.PIPE, text=True)
    try:
        t0 = time.monotonic()
        line = proc.stdout.readline()
        while ready not in line and time.monotonic() - t0 < 60:
            line = proc.stdout.readline()
        assert ready in line, f"{cmd[2]} did not start (no line with {ready!r})"
        time.sleep(settle)
        proc.send_signal(sig)
        out, _ = proc.communicate(timeout=15)
    finally:
        if proc.poll() is None:
            proc.kill()
    return proc.returncode, out


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
def test_a_deploy_tool_stops_cleanly_on_sigint_and_sigterm(sig):
    """A background job of a non-interactive shell starts with SIGINT ignored; systemd
    stops services with SIGTERM. Either signal runs the bridge's shutdown (its final
    summary line) and exits 0."""
    port = free_port()
    cmd = [sys.executable, "-m", "legged_casters.deploy.bridge", "--listen", f"tcp/127.0.0.1:{port}"]
    cmd += ["--namespace", f"sig{os.getpid()}"]
    returncode, out = signal_when_ready(cmd, "keys", sig)
    assert returncode == 0
    assert "bridge: state WAITING" in out  # the final summary: the finally block ran


@pytest.mark.realtime
def test_soak_short_form(tmp_path):
    """Half a minute of sim robot + bridge (the shipped caster policy) + random operator
    commands: the processes survive, the bridge answers the states with policy
    commands, no message is rejected, and the summary has what docs/deploy_measurements.md reports."""
    out = tmp_path / "soak"
    res = _run_soak(out, "--minutes", "0.5", "--report-every", "15", timeout=240)
    summary = json.loads((out / "summary.json").read_text())
    assert summary["crashed"] == {}
    assert summary["rejected"] == {}
    assert summary["policy_steps"] > 100  # the policy ran, not only stand-ups
    assert summary["latency"]["n"] > 1000  # ~50 answered states per second
    assert summary["latency"]["p50_ms"] < 20.0
    for name in ("bridge", "sim_robot"):
        assert summary["rss_mb"][name] > 10.0
    assert "stale-state faults" in res.stdout and "RSS bridge" in res.stdout
    for name in ("bridge", "sim_robot"):
        assert (out / f"{name}.log").read_text().strip()


@pytest.mark.realtime
def test_starts_short_form(tmp_path):
    """Two bridge starts through the stand-up against a synthetic standing robot: each
    bridge exits 0 and either answers the stand-up and the policy and reaches RUNNING, or
    latched a fault after this machine delayed the harness's own state (the robot side's
    fault, which the summary counts as such: docs/deploy.md, "Timing")."""
    out = tmp_path / "starts"
    res = _run_soak(out, "--starts", "2", "--run-seconds", "0.5", timeout=180)
    summary = json.loads((out / "starts.json").read_text())
    assert summary["starts"] == 2
    faulted = [r for r in summary["results"] if r["faults"]]
    for r in summary["results"]:
        assert r["returncode"] == 0
        if not r["faults"]:
            assert r["final_state"] == "RUNNING"
            assert r["latency"]["n"] > 50  # stand-up (2 s) and policy commands were answered
            # the worst state's way in (to the bridge's send, by the command's own stamp) and back
            assert r["worst_in_ms"] > 0.0 and r["worst_back_ms"] > 0.0
            assert r["worst_in_ms"] + r["worst_back_ms"] == pytest.approx(r["worst_ms"])
            # ... and the way in again, at the state's arrival in the bridge (its --trace)
            assert r["worst_transport_ms"] > 0.0 and r["worst_bridge_ms"] > 0.0
            assert r["worst_transport_ms"] + r["worst_bridge_ms"] == pytest.approx(r["worst_in_ms"])
    assert summary["bad_starts"] == len(faulted) == summary["bad_after_a_late_robot_state"], summary
    assert len(faulted) < 2, "both starts latched a fault after a late harness state: rerun on a quieter machine"
    assert "bridge starts" in res.stdout


def test_normal_priority_cmd_resets_an_inherited_fifo_policy():
    """A child of a SCHED_FIFO process starts under SCHED_OTHER through normal_priority_cmd."""
    probe = [sys.executable, "-c", "import os; print(os.sched_getscheduler(0))"]
    old = os.sched_getscheduler(0), os.sched_getparam(0)
    if not transport.set_realtime(5):
        pytest.skip("SCHED_FIFO not permitted here")
    try:
        inherited = subprocess.run(probe, capture_output=True, text=True).stdout.strip()
        reset = subprocess.run(transport.normal_priority_cmd(probe), capture_output=True, text=True).stdout.strip()
    finally:
        os.sched_setscheduler(0, old[0], old[1])
    assert inherited == str(os.SCHED_FIFO)
    assert reset == str(os.SCHED_OTHER)
