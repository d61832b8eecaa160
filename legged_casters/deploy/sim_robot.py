"""A simulated Go2 on the bridge's wire protocol: MuJoCo C, real time, over zenoh.

    python -m legged_casters.deploy.sim_robot --robot caster --connect tcp/127.0.0.1:7447

The robot starts from the MJCF's "stand" keyframe and runs one physics step per
``physics_dt`` of wall-clock time (absolute deadlines, sleeping in between). Each
step it

1. evaluates positions/velocities and the sensors (``mj_step1``); every
   ``1 / state_rate`` it publishes the state read from the named sensors
   (``imu_quat``, ``imu_gyro``, ``<joint>_pos``, ``<joint>_vel``), stamped with the
   step's scheduled time on the monotonic clock;
2. computes the joint torques from the newest joint command,
   ``tau = kp (q_target - q) + kd (dq_target - dq)``, clipped to the torque limits,
   and integrates (``mj_step2``).

The joints are the robot's action layout (``go2.action_layout``): 12 leg joints, and
for ``--robot wheel`` the 4 wheels after them. PD choice: the MJCF's actuators
(position servos for the legs, velocity servos for the wheels) are turned into
plain torque motors at load time (gain 1, no bias, no control range; their
``forcerange`` still clips at the torque limits), and ``ctrl`` is set to the torque
computed above from each message's own kp / kd. The ``<joint>_torque`` sensors keep
reading the applied torque.

Before the first command the robot holds its start pose with the Go2 default gains
(``--startup hold``, like the robot's own stand controller) or is passive
(``--startup damping``). When commands stop arriving for longer than
``--watchdog-ms``, it switches to damping (kp = 0, kd = ``--damping-kd``) until a new
command arrives. The state message reports what the robot is doing in
``robot_mode``. ``<ns>/sim/truth`` carries the trunk position and velocity for tests.
A command published in reply to a state is applied from the next physics step on:
one physics step (2 ms) of delay that the training env does not have.
"""

from __future__ import annotations

import argparse
import sys
import threading
import time

import mujoco
import numpy as np

from legged_casters.deploy import protocol as P
from legged_casters.deploy import robot_side, transport
from legged_casters.robot import build, go2


class SimRobot(robot_side.TakesCommands):
    def __init__(
        self,
        publish,
        robot: str = "caster",
        state_rate: float = 50.0,
        watchdog: float = 0.1,
        damping_kd: float = 1.0,
        startup: str = "hold",
    ):
        if robot not in build.MODEL_FILES:
            raise ValueError(f"--robot must be one of {list(build.MODEL_FILES)}")
        if startup not in ("hold", "damping"):
            raise ValueError("startup must be 'hold' or 'damping'")
        self.publish = publish
        self.model = mujoco.MjModel.from_xml_path(str(build.MODEL_FILES[robot]))
        m = self.model
        self.data = mujoco.MjData(m)
        key = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_KEY, build.STAND_KEY)
        mujoco.mj_resetDataKeyframe(m, self.data, key)
        self.dt = float(m.opt.timestep)
        self.decimation = max(1, int(round(1.0 / (state_rate * self.dt))))
        self.watchdog = watchdog
        self.startup = startup

        layout = go2.action_layout(robot)
        self.n = len(layout)
        act = [mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_ACTUATOR, build.actuator_name(j)) for j in layout.joints]
        if min(act) < 0:
            raise ValueError("model lacks an actuator named like FL_hip")
        self.act = np.asarray(act)
        m.actuator_gainprm[self.act, :] = 0.0
        m.actuator_gainprm[self.act, 0] = 1.0
        m.actuator_biasprm[self.act, :] = 0.0
        m.actuator_ctrllimited[self.act] = 0
        self.tau_limit = np.asarray(layout.torque_limits)
        jid = [mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_JOINT, j) for j in layout.joints]
        self.qadr = m.jnt_qposadr[jid]
        self.dadr = m.jnt_dofadr[jid]
        sl = {}
        for i in range(m.nsensor):
            name = mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_SENSOR, i)
            sl[name] = slice(int(m.sensor_adr[i]), int(m.sensor_adr[i] + m.sensor_dim[i]))
        self._quat, self._gyro = sl["imu_quat"], sl["imu_gyro"]
        self._qs = np.concatenate([np.arange(sl[f"{j}_pos"].start, sl[f"{j}_pos"].stop) for j in layout.joints])
        self._dqs = np.concatenate([np.arange(sl[f"{j}_vel"].start, sl[f"{j}_vel"].stop) for j in layout.joints])

        self.hold_q = self.data.qpos[self.qadr].copy()
        self.hold_kp, self.hold_kd = np.asarray(layout.kp), np.asarray(layout.kd)
        self.damp_kd = np.full(self.n, float(damping_kd))
        self._zeros = np.zeros(self.n)

        self.inbox = robot_side.CommandInbox(self.n)
        self.mode = P.CommandMode.HOLD if startup == "hold" else P.CommandMode.DAMPING
        self.mode_changes: list[tuple[float, P.CommandMode, str]] = [(time.monotonic(), self.mode, "")]
        """(when, new mode, why): what the live status prints."""
        self.state_sender = P.Sender()
        self.truth_sender = P.Sender()
        self.publish_state = threading.Event()
        self.publish_state.set()
        self.steps = 0
        self.overruns = 0
        self._running = False
        self._thread: threading.Thread | None = None

    # --- physics ---------------------------------------------------------------------
    def _gains(self, now: float) -> tuple:
        """(mode, why, q target, dq target, kp, kd) to apply now."""
        cmd, arrival = self.inbox.latest()
        z = self._zeros
        if cmd is None:
            if self.startup == "hold":
                return P.CommandMode.HOLD, "", self.hold_q, z, self.hold_kp, self.hold_kd
            return P.CommandMode.DAMPING, "start-up", self.hold_q, z, z, self.damp_kd
        return robot_side.command_targets(cmd, arrival, now, self.watchdog, self.damp_kd, self.hold_q)

    def step(self, now: float, stamp_ns: int) -> None:
        m, d = self.model, self.data
        mujoco.mj_step1(m, d)
        if self.steps % self.decimation == 0 and self.publish_state.is_set():
            self._publish_state(stamp_ns)
        mode, why, q_t, dq_t, kp, kd = self._gains(now)
        if mode != self.mode:
            self.mode = mode
            self.mode_changes.append((now, mode, why))
        q, dq = d.qpos[self.qadr], d.qvel[self.dadr]
        tau = kp * (q_t - q) + kd * (dq_t - dq)
        d.ctrl[self.act] = np.clip(tau, -self.tau_limit, self.tau_limit)
        mujoco.mj_step2(m, d)
        self.steps += 1

    def _publish_state(self, stamp_ns: int) -> None:
        s = self.data.sensordata
        h = self.state_sender.next_header()
        h.stamp_ns = stamp_ns
        msg = P.RobotState(
            quat=s[self._quat], gyro=s[self._gyro], q=s[self._qs], dq=s[self._dqs], robot_mode=self.mode, header=h
        )
        self.inbox.round_trip.sent(h.seq, time.monotonic())
        self.publish("state", msg.encode())
        th = self.truth_sender.next_header()
        th.stamp_ns = stamp_ns
        self.publish("truth", P.SimTruth(self.data.time, self.data.qpos[0:3], self.data.qvel[0:3], th).encode())

    def _loop(self) -> None:
        def overrun() -> None:
            self.overruns += 1

        robot_side.run_fixed_rate(
            self.dt, lambda: self._running, lambda now, deadline: self.step(now, int(deadline * 1e9)), overrun
        )

    def start(self) -> SimRobot:
        self._running = True
        self._thread = threading.Thread(target=self._loop, name="sim-robot", daemon=True)
        self._thread.start()
        return self

    def stop(self) -> None:
        self._running = False
        if self._thread is not None:
            self._thread.join(timeout=2.0)

    def trunk_height(self) -> float:
        return float(self.data.qpos[2])


class ZenohSimRobot:
    def __init__(self, session, namespace: str, **kwargs):
        self.keys = P.keys(namespace)
        self.pubs = {
            "state": transport.fast_publisher(session, self.keys["state"]),
            "truth": session.declare_publisher(self.keys["truth"]),
        }
        self.robot = SimRobot(lambda which, payload: self.pubs[which].put(payload), **kwargs)
        self.sub = session.declare_subscriber(self.keys["cmd"], lambda s: self.robot.on_command(s.payload.to_bytes()))

    def start(self) -> ZenohSimRobot:
        self.robot.start()
        return self

    def stop(self) -> None:
        self.robot.stop()
        self.sub.undeclare()
        for p in self.pubs.values():
            p.undeclare()


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--robot", choices=go2.FOOT_KINDS, default="caster")
    p.add_argument("--state-rate", type=float, default=50.0, help="state messages per second (default: 50)")
    p.add_argument("--watchdog-ms", type=float, default=100.0)
    p.add_argument("--damping-kd", type=float, default=1.0)
    p.add_argument("--startup", choices=("hold", "damping"), default="hold")
    p.add_argument("--duration", type=float, default=0.0, help="seconds (0: until Ctrl-C)")
    p.add_argument("--summary-every", type=float, default=10.0, help="seconds between status lines (0: none)")
    transport.add_zenoh_args(p, role="robot")
    args = p.parse_args(argv)
    try:
        session = transport.open_session(args)
    except transport.SessionError as err:
        print(f"sim_robot: error: {err}", file=sys.stderr)
        return 2
    zr = ZenohSimRobot(
        session,
        args.namespace,
        robot=args.robot,
        state_rate=args.state_rate,
        watchdog=args.watchdog_ms / 1e3,
        damping_kd=args.damping_kd,
        startup=args.startup,
    ).start()
    r = zr.robot
    print(f"sim_robot: {args.robot}, physics {1 / r.dt:.0f} Hz, state {1 / (r.dt * r.decimation):.0f} Hz", flush=True)
    watch, rates = robot_side.Watch("sim_robot", r.mode_changes), robot_side.Rates()

    def summary(seconds: float) -> None:
        (rate,) = rates(seconds, r.commands_received)
        rejected = {k: v for k, v in r.rejected.items() if v}
        print(
            f"sim_robot: {r.mode.name}, commands {rate:.1f}/s, {r.inbox.round_trip.summary()}, "
            f"sim time {r.steps * r.dt:.1f} s, overruns {r.overruns}, trunk z {r.data.qpos[2]:.2f} m, "
            f"rejected {rejected or 'none'}",
            flush=True,
        )

    def close() -> None:
        zr.stop()
        session.close()

    watch.serve(args.duration, args.summary_every, summary, close)
    print(
        f"sim_robot: {r.steps} steps ({r.steps * r.dt:.1f} s), commands {r.commands_received}, "
        f"rejected {r.rejected}, overruns {r.overruns}, mode {r.mode.name}, "
        f"trunk at ({r.data.qpos[0]:.3f}, {r.data.qpos[1]:.3f}, {r.data.qpos[2]:.3f}) m",
        flush=True,
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
