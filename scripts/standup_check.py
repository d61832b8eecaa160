"""The bridge's stand-up from the floor and its recovery after a fall, measured.

    python scripts/standup_check.py                         # 100 lying starts + 10 falls, ~4 min on 2 cores
    python scripts/standup_check.py --trials 20 --falls 0 --standup linear

The robot side is `legged_casters.deploy.sim_robot.SimRobot` (the caster model at 2 ms,
joint PD on the robot side) and the policy side is `legged_casters.deploy.bridge.Bridge`
with the shipped caster_omni policy: the same code the processes run, wired in this
process message by message (every payload is encoded and decoded), stepped as fast as
the CPU allows on the robot's clock. Only the timing rules that read this process's
clock are relaxed (the staleness limit, the operator timeout); docs/deploy.md tests
those over zenoh.

**Lying starts** (``--trials N``): each start is a state of the shipped policy skating
in caster_omni under a random command each (vx in [-1.5, 1.5] m/s, the training's vy
and wz, a fifth of them zero) at a random moment, then 3 s of damping (kp 0, kd 1, what a
robot does without commands): the pose a damped robot collapses into. Then the bridge
starts from WAITING with ``--standup`` and the robot has 4 s from the stand-up's first
command. Standing: trunk within 3 cm of the stand keyframe's height and tilted less
than 10 deg, from then to the end of the 4 s.

**Falls** (``--falls N``): from a stand-up on the floor, the policy skates at vx 0.5 for
2 s; a horizontal push in a random direction (100 N for 0.2 s at the trunk, 25 % more
every second until the bridge latches FALLEN) knocks it over; 2 s later the operator
sends a reset; the bridge stands it up again (rolling it onto its belly first when it lies
on its back or side; ``--no-righting``: without), the operator waits until the policy
runs and 1 s more, and the policy skates at vx 0.5 for 5 s. Success: no fault, upright at
the end (tilt under 10 deg, trunk above 0.25 m) and at least 1.5 m travelled.

**Loopback** (``--loopback N``): the real chain, each part its own process over zenoh on
this machine: ``sim_robot --startup damping`` (it collapses from its keyframe for 3 s;
with ``--robot go2``: ``fake_go2 --startup damping`` behind the Go2's DDS topics on
loopback and ``go2_adapter`` between them and zenoh, which needs ``./setup.sh unitree``),
then the bridge (``--policy``, ``--standup``; ``--max-state-age-ms 100``, so that a busy
machine cannot end the run on a late state), then an operator at 20 Hz: vx 0 until
the bridge runs and 1 s more, then vx 0.5 for 10 s. Measured from the simulator's truth
stream: the time from the bridge's start of the stand-up to standing, and over the
10 s the distance along the start heading, the lateral drift from that line and the
heading change.
"""

from __future__ import annotations

import argparse
import math
import os
import sys
import time
from pathlib import Path

import mujoco
import numpy as np
import torch

from legged_casters import registry
from legged_casters.deploy import protocol as P
from legged_casters.deploy import transport
from legged_casters.deploy.bench import module_cmd
from legged_casters.deploy.bridge import SHIPPED_POLICY, Bridge, BridgeConfig
from legged_casters.deploy.policy import PolicyRunner, load_meta, tilt_deg
from legged_casters.deploy.sim_robot import SimRobot
from legged_casters.robot import build
from legged_casters.tools.evaluate import EVAL_SETTINGS

STAND_TOLERANCE_M = 0.03
MAX_TILT_DEG = 10.0


def skating_states(n: int, seed: int, policy_dir: Path) -> tuple[np.ndarray, np.ndarray]:
    """(qpos, qvel) of n robots at random moments of skating (caster_omni, shipped policy)."""
    torch.set_num_threads(1)
    cfg, _ = registry.task_configs(
        "caster_omni", {**EVAL_SETTINGS, "num_envs": n, "episode_length_s": 60.0, "sim.backend": "cpu", "seed": seed}
    )
    cfg.commands.ranges.lin_vel_x = (-1.5, 1.5)
    env = registry.get_task("caster_omni").env_class(cfg)
    try:
        module = torch.jit.load(str(policy_dir / "policy.pt"), map_location="cpu").eval()
        rng = np.random.default_rng(seed)
        when = rng.integers(25, 300, n)
        still = rng.random(n) < 0.2
        qpos, qvel = np.zeros((n, env.sim.qpos.shape[1])), np.zeros((n, env.sim.qvel.shape[1]))
        cmd = env.commands.clone()  # each robot keeps the command its reset drew (set_commands stops resampling)
        cmd[torch.as_tensor(still)] = 0.0
        env.set_commands(cmd)
        obs = env.get_observations()
        for k in range(int(when.max()) + 1):
            with torch.no_grad():
                obs, _, _, _ = env.step(module(obs["policy"]))
            for i in np.nonzero(when == k)[0]:
                qpos[i], qvel[i] = env.sim.qpos[i].cpu().numpy(), env.sim.qvel[i].cpu().numpy()
        return qpos, qvel
    finally:
        env.close()


class Chain:
    """SimRobot + Bridge in one process, stepped on the robot's 2 ms clock."""

    def __init__(self, meta, runner, standup: str, qpos=None, qvel=None):
        self.robot = SimRobot(self._from_robot, robot=meta.robot, startup="damping", watchdog=1e9)
        self.bridge: Bridge | None = None
        self.meta, self.runner, self.standup = meta, runner, standup
        m, d = self.robot.model, self.robot.data
        if qpos is not None:
            d.qpos[:], d.qvel[:] = qpos, qvel
            mujoco.mj_forward(m, d)
        key = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_KEY, build.STAND_KEY)
        self.stand_z = float(m.key_qpos[key][2])
        self.trunk = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, "trunk")
        self.t = 0.0
        self.operator = P.Sender()

    def _from_robot(self, which: str, payload: bytes) -> None:
        if which == "state" and self.bridge is not None:
            self.bridge.on_state(payload)

    def _from_bridge(self, which: str, payload: bytes) -> None:
        if which == "cmd":
            self.robot.on_command(payload)

    def attach_bridge(self, **kw) -> Bridge:
        cfg = BridgeConfig(standup=self.standup, max_state_age=1e3, operator_timeout=0.0, **kw)
        self.bridge = Bridge(self.meta, cfg, self._from_bridge, self.runner)
        return self.bridge

    def operate(self, vx: float = 0.0, reset: bool = False) -> None:
        flags = P.OP_RESET if reset else 0
        self.bridge.on_operator(P.OperatorCommand(vx=vx, flags=flags, header=self.operator.next_header()).encode())

    def run(self, seconds: float, push: np.ndarray | None = None, push_s: float = 0.0) -> None:
        d = self.robot.data
        for k in range(int(round(seconds / self.robot.dt))):
            d.xfrc_applied[self.trunk, :3] = push if (push is not None and k * self.robot.dt < push_s) else 0.0
            self.robot.step(time.monotonic(), int(self.t * 1e9))
            self.t += self.robot.dt
        d.xfrc_applied[self.trunk, :3] = 0.0

    def tilt(self) -> float:
        """Degrees between the trunk's z axis and the vertical."""
        return tilt_deg(self.robot.data.qpos[3:7])

    def upright(self) -> bool:
        """Skating upright: tilted less than MAX_TILT_DEG, trunk above 0.25 m (it skates higher than it stands)."""
        return self.robot.data.qpos[2] > 0.25 and self.tilt() < MAX_TILT_DEG

    def standing(self) -> bool:
        return abs(self.robot.data.qpos[2] - self.stand_z) < STAND_TOLERANCE_M and self.tilt() < MAX_TILT_DEG

    def time_to_stand(self, seconds: float) -> float | None:
        """Run `seconds`; the time from which the robot stood to the end (None: not standing at the end)."""
        since, step = None, self.robot.dt
        for k in range(int(round(seconds / step))):
            self.run(step)
            since = (k * step if since is None else since) if self.standing() else None
        return since


def lying_starts(args, meta, runner) -> tuple[int, list[float], list[str]]:
    qpos, qvel = skating_states(args.trials, args.seed, args.policy)
    stood, times, failures = 0, [], []
    for i in range(args.trials):
        chain = Chain(meta, runner, args.standup, qpos[i], qvel[i])
        chain.run(3.0)  # no commands: the robot damps and collapses
        z0, tilt0 = float(chain.robot.data.qpos[2]), chain.tilt()
        chain.attach_bridge(righting=not args.no_righting)
        t = chain.time_to_stand(args.seconds)
        if t is not None and chain.bridge.state is P.BridgeState.RUNNING:
            stood += 1
            times.append(t)
        else:
            d = chain.robot.data
            failures.append(
                f"start {i}: lying at z {z0:.3f} m, tilted {tilt0:.0f} deg -> z {d.qpos[2]:.3f} m, tilted "
                f"{chain.tilt():.0f} deg, bridge {chain.bridge.state.name}"
                + (f" ({chain.bridge.fault.name})" if chain.bridge.fault else "")
                + "".join(f"; {note}" for note in chain.bridge.notes)
            )
        if (i + 1) % 10 == 0:
            print(f"[standup_check] lying starts {i + 1}/{args.trials}: {stood} stood", flush=True)
    return stood, times, failures


def knock_over(meta, runner, standup: str, rng, **bridge) -> tuple[Chain, float | None]:
    """A robot stood up on the floor, skating at vx 0.5 for 2 s, pushed in a random direction
    (100 N for 0.2 s, 25 % more every second) until the bridge latches FALLEN, then damped
    for 2 s: (the chain, the push that knocked it over in N; None if 1000 N did not)."""
    chain = Chain(meta, runner, standup)
    chain.run(1.0)
    chain.attach_bridge(**bridge)
    chain.run(4.0)
    chain.operate(0.5)
    chain.run(2.0)
    angle = rng.uniform(0.0, 2.0 * math.pi)
    force = 100.0
    while chain.bridge.fault is not P.Fault.FALLEN and force <= 1000.0:
        chain.run(1.0, push=force * np.array([math.cos(angle), math.sin(angle), 0.0]), push_s=0.2)
        force *= 1.25
    if chain.bridge.fault is not P.Fault.FALLEN:
        return chain, None
    chain.run(2.0)
    return chain, force / 1.25


def fall_recovery(args, meta, runner, rng) -> tuple[int, list[str]]:
    ok, notes = 0, []
    for i in range(args.falls):
        chain, force = knock_over(meta, runner, args.standup, rng, righting=not args.no_righting)
        if force is None:
            notes.append(f"fall {i}: pushes up to 1000 N for 0.2 s did not knock it over")
            print(f"[standup_check] {notes[-1]}", flush=True)
            continue
        lying = chain.tilt()
        b = chain.bridge
        notes_before = len(b.notes)
        chain.operate(0.0, reset=True)
        fold = b.folding.duration if b.folding else b.cfg.standup_time
        # every try may be a righting and a fold that fails at its very end
        longest = (b.righting.duration + fold) * b.righting.cfg.max_tries if b.righting else fold
        standup_s = 0.0
        while b.state is not P.BridgeState.RUNNING and b.fault is P.Fault.NONE and standup_s < longest + 1.0:
            chain.run(0.1)
            standup_s += 0.1
        chain.run(1.0)  # 1 s of vx 0
        chain.operate(0.5)
        x0 = chain.robot.data.qpos[:2].copy()
        chain.run(5.0)
        dist = float(np.linalg.norm(chain.robot.data.qpos[:2] - x0))
        good = chain.bridge.state is P.BridgeState.RUNNING and chain.upright() and dist >= 1.5
        ok += good
        notes.append(
            f"fall {i}: pushed with {force:.0f} N, lying tilted {lying:.0f} deg, "
            f"after reset {chain.bridge.state.name} ({len(b.notes) - notes_before} righting tries, stand-up "
            f"{standup_s:.1f} s)"
            + (f" ({chain.bridge.fault.name}: {chain.bridge.fault_detail})" if chain.bridge.fault else "")
            + f", trunk at {chain.robot.data.qpos[2]:.3f} m (stand {chain.stand_z:.3f}), tilt {chain.tilt():.0f} deg, "
            f"{dist:.2f} m in 5 s at vx 0.5: " + ("ok" if good else "FAILED")
        )
        print(f"[standup_check] {notes[-1]}", flush=True)
    return ok, notes


def loopback(args, i: int) -> dict | None:
    """One run of the process chain from lying; None if it did not come up."""
    import subprocess

    import zenoh

    port = 17900 + (os.getpid() + i) % 90
    ns, endpoint = f"standup{os.getpid()}_{i}", f"tcp/127.0.0.1:{port}"
    session = zenoh.open(transport.make_config("peer", listen=[endpoint]))
    keys = P.keys(ns)
    truths, statuses = [], []
    subs = [
        session.declare_subscriber(keys["truth"], lambda s: truths.append(P.SimTruth.decode(s.payload.to_bytes()))),
        session.declare_subscriber(
            keys["status"], lambda s: statuses.append(P.BridgeStatus.decode(s.payload.to_bytes()))
        ),
    ]
    op_pub, op = session.declare_publisher(keys["operator"]), P.Sender()
    common = ["--connect", endpoint, "--namespace", ns, "--summary-every", "0"]
    if args.robot == "sim":
        robot = [module_cmd("sim_robot", "--startup", "damping", *common)]
    else:  # the Go2's DDS interface: the fake Go2 behind rt/lowstate and rt/lowcmd, the adapter to zenoh
        dds = ["--domain-id", str(100 + (os.getpid() + i) % 100)]
        robot = [
            module_cmd("fake_go2", "--startup", "damping", *dds, *common),
            module_cmd("go2_adapter", *dds, *common),
        ]
    procs = [subprocess.Popen(cmd, stdout=subprocess.DEVNULL) for cmd in robot]

    def operate(vx: float, seconds: float, until=None) -> None:
        end = time.monotonic() + seconds
        while time.monotonic() < end and not (until and until()):
            op_pub.put(P.OperatorCommand(vx=vx, header=op.next_header()).encode())
            time.sleep(0.05)

    try:
        operate(0.0, 30.0, until=lambda: len(truths) > 0)
        t_robot = time.monotonic()
        operate(0.0, 3.0)  # the robot collapses under damping
        lying_z = truths[-1].pos[2]
        procs.append(subprocess.Popen(
            module_cmd(
                "bridge", "--policy", str(args.policy), "--standup", args.standup, "--max-state-age-ms", "100",
                "--heading-hold", str(args.heading_hold), *common,
            ),
            stdout=subprocess.DEVNULL,
        ))  # fmt: skip

        def state_is(s) -> bool:
            return bool(statuses) and statuses[-1].state == s

        operate(0.0, 30.0, until=lambda: state_is(P.BridgeState.STANDUP) or state_is(P.BridgeState.RUNNING))
        n0 = len(truths)
        # a stand-up takes about 3 s, up to max_tries righting-and-fold tries when it tips;
        # a busy machine runs the robot side behind real time: wait while it is standing up
        operate(0.0, 40.0, until=lambda: not state_is(P.BridgeState.STANDUP))
        operate(0.0, 1.0)
        if not state_is(P.BridgeState.RUNNING):
            last = statuses[-1] if statuses else None
            why = "no status" if last is None else f"{P.BridgeState(last.state).name} ({P.Fault(last.fault).name})"
            print(f"[standup_check] the bridge is not running: {why}", flush=True)
            return None
        rise = truths[n0:]
        stand_t = next((t.sim_time - rise[0].sim_time for t in rise if t.pos[2] > 0.3), math.nan)
        start = truths[-1]
        operate(0.5, 10.0)
        seg = np.array([t.pos[:2] for t in truths if t.sim_time >= start.sim_time])
        # the truth stream has no orientation: the start heading is the direction of the first metre
        # travelled, the heading change that of the last 50 states' path against it
        d = seg - seg[0]
        k = int(np.argmax(np.linalg.norm(d, axis=1) > 1.0)) or len(d) - 1
        u = d[k] / max(np.linalg.norm(d[k]), 1e-9)
        along = float(d[-1] @ u)
        lateral = float(np.abs(d[:, 0] * u[1] - d[:, 1] * u[0]).max())
        v_end = d[-1] - d[-min(len(d), 50)]
        turn = math.degrees(math.atan2(u[0] * v_end[1] - u[1] * v_end[0], u @ v_end))
        return {
            "lying_z": lying_z, "stand_s": stand_t, "along_m": along, "lateral_m": lateral, "turn_deg": turn,
            "fault": P.Fault(statuses[-1].fault).name, "state": P.BridgeState(statuses[-1].state).name,
            "robot_s": time.monotonic() - t_robot,
        }  # fmt: skip
    finally:
        for p in reversed(procs):
            p.terminate()
        for p in procs:
            try:
                p.wait(10)
            except subprocess.TimeoutExpired:
                p.kill()
        for sub in subs:
            sub.undeclare()
        op_pub.undeclare()
        session.close()


def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--policy", type=Path, default=SHIPPED_POLICY, help="exported caster policy (folder)")
    ap.add_argument("--trials", type=int, default=100, help="lying starts")
    ap.add_argument("--falls", type=int, default=10, help="push-induced falls to recover from")
    ap.add_argument("--loopback", type=int, default=0, help="runs of the process chain over zenoh (sim_robot, bridge)")
    ap.add_argument(
        "--robot",
        choices=("sim", "go2"),
        default="sim",
        help="loopback robot side: sim_robot, or fake_go2 + go2_adapter over DDS (./setup.sh unitree)",
    )
    ap.add_argument("--standup", choices=("fold", "linear"), default="fold")
    ap.add_argument("--seconds", type=float, default=4.0, help="time a lying start has to stand (s)")
    ap.add_argument("--no-righting", action="store_true", help="the bridge's --no-righting (lying starts and falls)")
    ap.add_argument("--heading-hold", type=float, default=0.0, help="the bridge's --heading-hold gain (loopback runs)")
    ap.add_argument("--seed", type=int, default=0)
    return ap


def main(argv: list[str] | None = None) -> int:
    ap = build_parser()
    args = ap.parse_args(argv)
    if min(args.trials, args.falls, args.loopback, args.heading_hold) < 0:
        ap.error("--trials, --falls, --loopback and --heading-hold must be >= 0")
    meta = load_meta(args.policy)
    if meta.robot != "caster":
        ap.error(f"--policy {args.policy} drives the {meta.robot!r} robot; this check is for the caster robot")
    if args.loopback and args.robot == "go2":
        from legged_casters.deploy import unitree

        try:
            unitree.load_sdk()
        except unitree.SdkUnavailable as err:
            ap.error(f"--robot go2 needs the Unitree SDK: {err}")
    runner = PolicyRunner(meta, "onnx")
    t0 = time.time()
    if args.trials:
        stood, times, failures = lying_starts(args, meta, runner)
        for f in failures:
            print(f"[standup_check] {f}")
        tt = np.asarray(times) if times else np.zeros(1)
        print(
            f"[standup_check] lying starts: {stood}/{args.trials} standing within {args.seconds:g} s "
            f"(--standup {args.standup}); standing from {np.median(tt):.2f} s (median), {tt.max():.2f} s (max)",
            flush=True,
        )
    if args.falls:
        ok, _ = fall_recovery(args, meta, runner, np.random.default_rng(args.seed))
        print(f"[standup_check] falls: {ok}/{args.falls} stood up and skated again after a reset", flush=True)
    runs = []
    for i in range(args.loopback):
        r = loopback(args, i)
        runs.append(r)
        print(f"[standup_check] loopback {i}: " + ("the bridge never ran" if r is None else (
            f"lying at z {r['lying_z']:.3f} m, trunk above 0.3 m {r['stand_s']:.2f} s after the stand-up began; "
            f"vx 0.5 for 10 s: {r['along_m']:.2f} m along the start heading, lateral drift {r['lateral_m']:.2f} m, "
            f"heading change {r['turn_deg']:+.0f} deg; bridge {r['state']}"
            + (f" ({r['fault']})" if r["fault"] != "NONE" else "")
        )), flush=True)  # fmt: skip
    if args.loopback:
        good = [r for r in runs if r is not None and r["fault"] == "NONE" and r["state"] == "RUNNING"]
        print(
            f"[standup_check] loopback ({args.robot}): {len(good)}/{args.loopback} stood up from lying and skated",
            flush=True,
        )
    print(f"[standup_check] {time.time() - t0:.0f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
