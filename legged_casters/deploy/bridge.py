"""The policy bridge: robot state in, joint commands out, over zenoh.

    python -m legged_casters.deploy.bridge --policy exported/ --listen tcp/127.0.0.1:7447

Everything about the policy comes from the export (policy.yaml + policy.onnx or
policy.pt). The control loop and its safety rules (docs/deploy.md has the details):

* Clock. The robot's state stream is the steady clock: a policy step is taken on
  the first state whose robot timestamp reaches the next absolute deadline
  ``t0 + k * control_dt`` (within ``--stamp-tolerance-ms``), in the subscriber's
  thread as the state arrives, so a command answers the state it was computed from
  with only transport + inference latency, and the period is the robot's, not this
  process's. A supervisor thread on the bridge's own monotonic clock sleeps to
  absolute deadlines (a condition variable, no spinning) for the state-staleness
  limit, the damping commands while faulted and the status messages. With
  ``--clock local`` that thread also takes the control steps, at its own absolute
  deadlines, from the newest state.
* WAITING: nothing is published until a valid state has arrived.
* STANDUP: with ``--standup fold`` (the default) the legs fold, tuck under the trunk and
  lift to ``default_joint_pos`` (the lift takes ``--standup-time``) with attitude feedback
  from the IMU, which stands a caster robot up from the floor
  (legged_casters.deploy.standup). Before the fold, a robot tilted more than 40 deg (on
  its back or side, after a fall) is first rolled onto its belly by the legs' righting
  keyframes, up to 3 tries, else DAMPING with fault FALLEN (``--no-righting``: off); with
  ``--standup linear`` the leg targets ramp from
  the measured pose to ``default_joint_pos`` over ``--standup-time``. Export gains;
  driving wheels are held still (velocity target 0). Then the policy runs (RUNNING).
* RUNNING with the trunk tilted more than ``--max-tilt-deg`` from upright (default 45;
  0: off): fallen, DAMPING until an operator reset, which stands it up again.
* State older than ``--max-state-age-ms`` (default 1.5 control periods) or a
  non-finite policy output: DAMPING (kp = 0, kd = ``--damping-kd``), published every
  control period, latched until an operator reset. A non-finite output is never
  published. Targets are clipped to ``joint_pos_limits`` (rad; for a wheel, whose
  policy action is a velocity target, rad/s).
* Operator stop: STOPPED (damping), latched until a message with the reset flag;
  reset goes back to WAITING, and the next fresh state starts a new stand-up.
* Every received payload is decoded and checked (length, magic, version, finite
  values, ranges, sequence order); a bad one is dropped and counted by reason in
  the status, and never triggers a command. A state may skip at most
  ``state_window`` seqs (60 with the default staleness limit); entering WAITING (an
  operator reset) re-anchors the sequence, so the next valid state is accepted
  whatever its seq.
* Operator stream (protocol.OperatorFilter): a valid stop is acted on whatever its seq
  or epoch; other operator messages are checked against a 64-seq window that accepts
  each seq once and follows a jump further ahead, or a new epoch, only when a second
  message continues it, so no single message can lock the operator out.
"""

from __future__ import annotations

import argparse
import collections
import dataclasses
import math
import sys
import threading
import time
import traceback
from pathlib import Path

import numpy as np

from legged_casters.deploy import protocol as P
from legged_casters.deploy import transport
from legged_casters.deploy.policy import (
    ObservationBuilder,
    PolicyFormatError,
    PolicyMeta,
    PolicyRunner,
    gravity_tilt_deg,
    load_meta,
    projected_gravity,
    tilt_deg,
    yaw_of,
)
from legged_casters.deploy.standup import Righting, RightingCfg, StandUp, StandUpCfg

MAX_STATE_RATE_HZ = 1000.0
"""The fastest robot state stream the bridge expects (a Go2 publishes LowState at 500 Hz)."""
TRACE_STEPS = 180_000
"""Commands `--trace` keeps: the last hour at 50 Hz."""


def state_window(max_state_age: float) -> int:
    """How many seqs a robot state may skip: as many as a MAX_STATE_RATE_HZ stream sends in
    twice the staleness limit (60 with the default 30 ms). A real stream that skips more
    sent nothing for longer than the limit, so the bridge has latched STALE_STATE already
    and its reset re-anchors the sequence; a single message that jumps further ahead is
    rejected and changes nothing."""
    return max(1, math.ceil(2.0 * max_state_age * MAX_STATE_RATE_HZ))


@dataclasses.dataclass
class BridgeConfig:
    backend: str = "onnx"
    standup: str = "fold"  # "fold": legged_casters.deploy.standup; "linear": a ramp to the default pose
    standup_time: float = 2.0  # s: the fold stand-up's lift, or the whole linear ramp
    max_tilt_deg: float = 45.0  # RUNNING with the trunk tilted more than this: FALLEN (0: off)
    righting: bool = True  # fold stand-up: first roll a robot lying on its back or side onto its belly
    max_state_age: float | None = None  # s; None: 1.5 control periods
    damping_kd: float = 1.0
    operator_timeout: float = 1.0  # s without operator messages -> zero velocity command; 0: never
    max_command: tuple[float, float, float] = (1.0, 1.0, 1.5)  # |vx|, |vy|, |wz| limits
    stamp_tolerance: float = 0.001  # s
    clock: str = "robot"  # "robot": step on the state stream's timestamps; "local": on this process's clock
    status_period: float = 0.1  # s
    heading_hold: float = 0.0  # rad/s per rad: while told to move with wz 0, turn back to the latched yaw (0: off)

    def __post_init__(self):
        if not (self.heading_hold >= 0 and math.isfinite(self.heading_hold)):
            raise ValueError(f"heading_hold must be a finite gain >= 0 (0: off), got {self.heading_hold!r}")


class RateStats:
    """Policy-step periods over a sliding window."""

    def __init__(self, nominal: float, window: int = 1000):
        self.nominal = nominal
        self.periods: collections.deque[float] = collections.deque(maxlen=window)
        self.inference: collections.deque[float] = collections.deque(maxlen=window)
        self.last: float | None = None

    def step(self, now: float) -> None:
        if self.last is not None:
            self.periods.append(now - self.last)
        self.last = now

    def reset(self) -> None:
        self.last = None

    def summary(self, periods: np.ndarray | None = None) -> dict[str, float]:
        """Rate and jitter of `periods` (s; default: this window's)."""
        p = np.asarray(self.periods if periods is None else periods, np.float64)
        if p.size == 0:
            return {"rate_hz": 0.0, "period_mean_ms": 0.0, "jitter_p99_ms": 0.0, "jitter_max_ms": 0.0}
        jit = np.abs(p - self.nominal)
        return {
            "rate_hz": float(1.0 / p.mean()),
            "period_mean_ms": float(p.mean() * 1e3),
            "jitter_p99_ms": float(np.percentile(jit, 99) * 1e3),
            "jitter_max_ms": float(jit.max() * 1e3),
        }


class Bridge:
    """State machine + control loop. `publish(key, payload)` sends a message; the zenoh
    wiring is in `ZenohBridge`, so this class can also be driven directly."""

    def __init__(self, meta: PolicyMeta, config: BridgeConfig, publish, runner=None):
        self.meta = meta
        self.cfg = config
        self.publish = publish
        self.runner = runner or PolicyRunner(meta, config.backend)
        self.obs = ObservationBuilder(meta)
        self.dt = meta.control_dt
        self.max_state_age = config.max_state_age if config.max_state_age is not None else 1.5 * self.dt
        self.default = meta.default_joint_pos.astype(np.float64)
        self.lo, self.hi = meta.joint_pos_limits[:, 0], meta.joint_pos_limits[:, 1]
        self.kp, self.kd = meta.kp.astype(np.float64), meta.kd.astype(np.float64)
        self.n = meta.num_joints
        self.position = meta.position_mask
        """Position joints (legs) vs velocity joints (wheels: kp 0, a dq target)."""
        self.damp_kd = np.full(self.n, float(config.damping_kd))
        modes = meta.propulsion_modes
        self.mode_masks = {m: np.asarray(modes[m.key], np.float64) for m in P.PropulsionMode if m.key in modes}
        if not self.mode_masks:  # a policy without propulsion modes (wheel robot, point feet): the default only
            self.mode_masks = {P.PropulsionMode.FOUR_WHEEL: np.zeros(4)}

        self._cv = threading.Condition()
        self._running = False
        self._thread: threading.Thread | None = None
        self.state_filter = P.SequenceFilter(window=state_window(self.max_state_age))
        self.operator_filter = P.OperatorFilter()
        self.cmd_sender = P.Sender()
        self.status_sender = P.Sender()

        # shared with the callbacks (guarded by _cv)
        self._latest: P.RobotState | None = None
        self._latest_arrival = 0.0
        self.commands = np.zeros(3)
        self.mode_mask = self.mode_masks.get(P.PropulsionMode.FOUR_WHEEL, np.zeros(4))
        self._operator_arrival = -1.0
        self.rejected = dict.fromkeys(P.REJECT_REASONS, 0)
        self.received_state = 0
        self.received_operator = 0

        # control-thread state
        self.state = P.BridgeState.WAITING
        self.fault = P.Fault.NONE
        self.last_actions = np.zeros(self.n, np.float32)
        self.running_steps = 0
        self.next_stamp: int | None = None
        self.standup_from: np.ndarray | None = None
        self.standup_step = 0
        self.policy_steps = 0
        self.commands_sent = 0
        self.last_cmd_seq = 0
        self.trace: collections.deque | None = None  # (state seq, its arrival ns, the answer's send ns); start_trace
        self.rate = RateStats(self.dt)
        self._next_damping = 0.0
        self._next_status = 0.0
        self._last_step = 0.0
        self._next_tick = 0.0  # clock == "local": the next absolute deadline
        self._waiting_since = 0.0
        if config.clock not in ("robot", "local"):
            raise ValueError(f"clock must be 'robot' or 'local', got {config.clock!r}")
        if config.standup not in ("fold", "linear"):
            raise ValueError(f"standup must be 'fold' or 'linear', got {config.standup!r}")
        self.folding = (
            StandUp(meta.joint_names, self.default, StandUpCfg(lift_time=config.standup_time))
            if config.standup == "fold"
            else None
        )
        self.righting = (
            Righting(meta.joint_names, RightingCfg(), meta.joint_pos_limits)
            if self.folding is not None and config.righting
            else None
        )
        self.righting_side: float | None = None  # while righting: +1 left side down, -1 right side down
        self.standup_tries = 0
        self.heading_ref: float | None = None
        """Heading hold: the yaw (rad) latched when the operator last asked to move without turning."""
        self.transitions: list[tuple[float, P.BridgeState, P.Fault]] = []
        self.notes: list[str] = []  # events inside a state (righting tries), for the CLI to print
        self.fault_detail = ""
        """What tripped the last stale-state fault, in words (printed with the transition)."""

    # --- inputs (called from zenoh callback threads) ----------------------------------
    def _reject(self, err: P.ProtocolError) -> None:
        self.rejected[err.reason] += 1

    def on_state(self, payload: bytes) -> None:
        now = time.monotonic()
        with self._cv:
            try:
                msg = P.RobotState.decode(payload)
                if len(msg.q) != self.n:
                    raise P.ProtocolError("malformed", f"state has {len(msg.q)} joints, the policy drives {self.n}")
                self.state_filter.check(msg.header)
            except P.ProtocolError as e:
                self._reject(e)
                return
            self.received_state += 1
            self._check_stale(now)  # a state arriving after the limit does not undo the fault
            self._latest = msg
            self._latest_arrival = now
            # the control step runs right here, in the subscriber's thread: no hand-off latency
            try:
                if self.cfg.clock == "robot" and (
                    self.state is P.BridgeState.WAITING
                    or (self.state in (P.BridgeState.STANDUP, P.BridgeState.RUNNING) and self._due(msg.header.stamp_ns))
                ):
                    self._control_step(msg, now)
            except Exception:  # a bug or a failing runtime must not leave the robot on its last target
                traceback.print_exc()
                self._enter(P.BridgeState.DAMPING, P.Fault.INTERNAL_ERROR)
            self._cv.notify()  # new stale deadline for the supervisor

    def on_operator(self, payload: bytes) -> None:
        now = time.monotonic()
        with self._cv:
            try:
                msg = P.OperatorCommand.decode(payload)
            except P.ProtocolError as e:
                self._reject(e)
                return
            if msg.stop:
                self._on_stop(msg, now)
                return
            try:
                mask = self.mode_masks.get(P.PropulsionMode(msg.propulsion))
                if mask is None:
                    raise P.ProtocolError(
                        "out_of_range", f"propulsion mode {P.PropulsionMode(msg.propulsion).key} not in the export"
                    )
                self.operator_filter.check(msg.header)
            except P.ProtocolError as e:
                self._reject(e)
                return
            self.received_operator += 1
            self._take_command(msg, mask, now)
            if msg.reset and self.state in (P.BridgeState.STOPPED, P.BridgeState.DAMPING):
                self._enter(P.BridgeState.WAITING)  # the next state starts a new stand-up
            self._cv.notify()

    def _take_command(self, msg: P.OperatorCommand, mask, now: float) -> None:
        lim = np.asarray(self.cfg.max_command)
        self.commands = np.clip([msg.vx, msg.vy, msg.wz], -lim, lim)
        self.mode_mask = mask
        self._operator_arrival = now

    def _on_stop(self, msg: P.OperatorCommand, now: float) -> None:
        """A valid stop is acted on whatever its sequence number, epoch or propulsion mode:
        stopping is always safe, so no earlier message can make a stop be dropped. Only a
        stop that is also in order (and names a propulsion mode of the export) updates the
        velocity command and the sequence filter's state."""
        self.received_operator += 1
        mask = self.mode_masks.get(P.PropulsionMode(msg.propulsion))
        try:
            self.operator_filter.check(msg.header)
            if mask is not None:
                self._take_command(msg, mask, now)
        except P.ProtocolError:
            pass  # out of order: stop anyway, take nothing else from it
        if self.state is not P.BridgeState.STOPPED:
            self._enter(P.BridgeState.STOPPED, P.Fault.OPERATOR_STOP)
        self._cv.notify()

    # --- outputs ------------------------------------------------------------------------
    def _send_command(self, mode: P.CommandMode, q, kp, kd, state_seq: int, dq=None) -> None:
        h = self.cmd_sender.next_header()
        dq = list(dq) if dq is not None else None
        self.publish("cmd", P.JointCommand(int(mode), list(q), list(kp), list(kd), state_seq, h, dq).encode())
        self.commands_sent += 1
        self.last_cmd_seq = h.seq
        if self.trace is not None and state_seq != P.NO_STATE_SEQ:  # the state answered is the newest
            self.trace.append((state_seq, int(self._latest_arrival * 1e9), h.stamp_ns))

    def start_trace(self, steps: int = TRACE_STEPS) -> None:
        """Keep, for the last `steps` commands that answer a state, the state's seq, its
        arrival here and the command's send (its header stamp), both CLOCK_MONOTONIC ns:
        the way from the robot's put to this bridge's send splits there into the state's
        transport and the bridge's own step."""
        self.trace = collections.deque(maxlen=steps)

    def write_trace(self, path: Path) -> int:
        """The trace as CSV (state_seq, arrival_ns, sent_ns); returns its row count."""
        with self._cv:
            rows = list(self.trace or ())
        path.write_text("state_seq,arrival_ns,sent_ns\n" + "".join(f"{a},{b},{c}\n" for a, b, c in rows))
        return len(rows)

    def _clip_q(self, q) -> np.ndarray:
        """Position joints' targets inside their limits; velocity joints' angles as given
        (their kp is 0, the angle is only reported)."""
        q = np.asarray(q, np.float64)
        return np.where(self.position, np.clip(q, self.lo, self.hi), q)

    def _send_damping(self, state_seq: int = P.NO_STATE_SEQ) -> None:
        q = self._latest.q if self._latest is not None else self.default
        self._send_command(P.CommandMode.DAMPING, self._clip_q(q), np.zeros(self.n), self.damp_kd, state_seq)

    def status(self) -> P.BridgeStatus:
        """The status message. Only copies are made under the lock; the statistics are
        computed after it is released, so a state arriving meanwhile is not held up."""
        with self._cv:
            age = (time.monotonic() - self._latest_arrival) * 1e3 if self._latest is not None else 0.0
            periods = np.fromiter(self.rate.periods, np.float64, len(self.rate.periods))
            inference = np.fromiter(self.rate.inference, np.float64, len(self.rate.inference))
            fields = dict(
                state=self.state,
                fault=self.fault,
                rejected=[self.rejected[r] for r in P.REJECT_REASONS],
                last_state_seq=self.state_filter.last_seq if self.state_filter.last_seq >= 0 else 0,
                last_operator_seq=self.operator_filter.last_seq if self.operator_filter.last_seq >= 0 else 0,
                last_cmd_seq=self.last_cmd_seq,
                received_state=self.received_state,
                received_operator=self.received_operator,
                commands=self.commands_sent,
                policy_steps=self.policy_steps,
                state_age_ms=age,
                header=self.status_sender.next_header(),
            )
        inf = float(inference.mean() * 1e3) if inference.size else 0.0
        return P.BridgeStatus(inference_mean_ms=inf, **fields, **self.rate.summary(periods))

    # --- state machine ------------------------------------------------------------------
    def _enter(self, state: P.BridgeState, fault: P.Fault = P.Fault.NONE) -> None:
        self.state, self.fault = state, fault
        self.transitions.append((time.monotonic(), state, fault))
        if state in (P.BridgeState.DAMPING, P.BridgeState.STOPPED):
            self._send_damping()
            self._next_damping = time.monotonic() + self.dt
            self.rate.reset()
        if state is P.BridgeState.WAITING:
            # The next valid state is accepted whatever its seq: one message that moved the
            # sequence ahead of the real stream cannot keep the robot from standing up again.
            self.state_filter.reanchor()
            self._waiting_since = time.monotonic()
            self.next_stamp = None
            self.rate.reset()

    def _retry_righting(self, msg: P.RobotState, gravity: np.ndarray, where: str) -> bool:
        """One more stand-up try, righting from the pose in `msg`; after `max_tries` tries,
        DAMPING with fault FALLEN instead (returns False)."""
        self.standup_tries += 1
        if self.standup_tries >= self.righting.cfg.max_tries:
            self.fault_detail = (
                f"trunk tilted {gravity_tilt_deg(gravity):.0f} deg {where}, after {self.standup_tries} stand-up tries"
            )
            self._enter(P.BridgeState.DAMPING, P.Fault.FALLEN)
            return False
        self.standup_from, self.standup_step = np.asarray(msg.q, np.float64), 0
        self._start_righting(gravity, force=True)
        return True

    def _start_righting(self, gravity: np.ndarray, force: bool = False) -> None:
        """Start righting from the pose in `standup_from` if the trunk is tilted past the
        start limit or `force` (and righting is on); else `righting_side` is None."""
        needed = self.righting is not None and (force or self.righting.needed(gravity))
        self.righting_side = float(Righting.side_down(gravity)) if needed else None
        if needed:
            side = "left" if self.righting_side > 0 else "right"
            self.notes.append(
                f"STANDUP: righting, try {self.standup_tries + 1} of {self.righting.cfg.max_tries} (trunk tilted "
                f"{gravity_tilt_deg(gravity):.0f} deg, {side} side down)"
            )

    def _due(self, stamp_ns: int) -> bool:
        """Is a state with this robot timestamp the one for the next control step?"""
        if self.next_stamp is None:
            self.next_stamp = stamp_ns
        dt_ns = int(round(self.dt * 1e9))
        if stamp_ns < self.next_stamp - int(self.cfg.stamp_tolerance * 1e9):
            if self.next_stamp - stamp_ns > 2 * dt_ns:  # the robot's clock jumped back (restart): re-anchor
                self.next_stamp = stamp_ns + dt_ns
                return True
            return False
        late = stamp_ns - self.next_stamp
        self.next_stamp = self.next_stamp + dt_ns if late < dt_ns else stamp_ns + dt_ns
        return True

    def _control_step(self, msg: P.RobotState, now: float) -> None:
        seq = msg.header.seq
        self._last_step = now
        if self.state is P.BridgeState.WAITING:
            self.standup_from = np.asarray(msg.q, np.float64)
            self.standup_step = 0
            self.last_actions[:] = 0.0
            self.standup_tries = 0
            self._start_righting(projected_gravity(msg.quat))
            self._enter(P.BridgeState.STANDUP)
            self.next_stamp = msg.header.stamp_ns + int(round(self.dt * 1e9))
        if self.state is P.BridgeState.STANDUP:
            self.standup_step += 1
            gravity = projected_gravity(msg.quat)
            if (
                self.righting is not None
                and self.righting_side is None
                and self.righting.needed(gravity, self.righting.cfg.abort_tilt_deg)
            ):  # the fold tipped the robot over: right it again from where it lies
                if not self._retry_righting(msg, gravity, "during the fold"):
                    return
                self.standup_step = 1
            if self.righting_side is not None:
                t = self.standup_step * self.dt
                q = self.righting.targets(t, self.standup_from, self.righting_side)
                if t >= self.righting.duration:  # judge the tilt: the fold, or another try, starts from here
                    if self.righting.needed(gravity):
                        if not self._retry_righting(msg, gravity, "after righting"):
                            return
                    else:
                        self.righting_side = None
                        self.standup_from, self.standup_step = np.asarray(msg.q, np.float64), 0
                q = np.where(self.position, q, msg.q)
                self._send_command(P.CommandMode.STANDUP, self._clip_q(q), self.kp, self.kd, seq)
                self.rate.step(now)
                return
            if self.folding is not None:
                t = self.standup_step * self.dt
                q = self.folding.targets(t, self.standup_from, gravity)
                done = t >= self.folding.duration
            else:
                n = max(1, int(round(self.cfg.standup_time / self.dt)))
                alpha = min(1.0, self.standup_step / n)
                q = self.standup_from + alpha * (self.default - self.standup_from)
                done = alpha >= 1.0
            # Wheels (velocity joints) are held still: dq target 0 with their kd.
            q = np.where(self.position, q, msg.q)
            self._send_command(P.CommandMode.STANDUP, self._clip_q(q), self.kp, self.kd, seq)
            self.rate.step(now)
            if done and self.righting is not None and self.righting.needed(gravity, self.righting.cfg.stood_tilt_deg):
                # the fold ended with the robot still lying tilted (e.g. on its side): no policy, right it again
                self._retry_righting(msg, gravity, "after the fold")
                return
            if done:
                self._enter(P.BridgeState.RUNNING)
                self.running_steps = 0  # the policy's gait clock starts with the policy
                self.heading_ref = None
            return
        # RUNNING
        if self.cfg.max_tilt_deg > 0 and (tilt := tilt_deg(msg.quat)) > self.cfg.max_tilt_deg:
            self.fault_detail = f"trunk tilted {tilt:.0f} deg from upright (limit {self.cfg.max_tilt_deg:g})"
            self._enter(P.BridgeState.DAMPING, P.Fault.FALLEN)
            return
        if self.cfg.operator_timeout > 0 and now - self._operator_arrival > self.cfg.operator_timeout:
            commands = np.zeros(3)
        else:
            commands = self.commands
        if self.cfg.heading_hold > 0:
            commands = self._hold_heading(commands, msg.quat)
        obs = self.obs.build(msg, commands, self.mode_mask, self.last_actions, self.running_steps)
        self.running_steps += 1
        t0 = time.perf_counter()
        actions = self.runner(obs)
        self.rate.inference.append(time.perf_counter() - t0)
        self.policy_steps += 1
        if not np.all(np.isfinite(actions)):
            self._enter(P.BridgeState.DAMPING, P.Fault.NONFINITE_ACTION)
            return
        clip = self.meta.clip_actions
        actions = np.clip(actions, -clip, clip)
        q_t, dq_t = self.meta.targets(actions, np.asarray(msg.q, np.float64))
        self._send_command(P.CommandMode.POLICY, q_t, self.kp, self.kd, seq, dq_t)
        self.last_actions[:] = actions
        self.rate.step(now)

    def _hold_heading(self, commands: np.ndarray, quat) -> np.ndarray:
        """Heading hold (legged_gym's heading command): while the operator asks to move
        (vx or vy not 0) with wz 0, the policy is told wz = heading_hold x (latched yaw -
        yaw now), wrapped to +-pi and clipped to max_command's |wz|. The yaw is latched at
        the first such step since the last release; a command with wz, or a zero command,
        releases it (one straight command followed by another keeps the latch)."""
        if commands[2] != 0.0 or (commands[0] == 0.0 and commands[1] == 0.0):
            self.heading_ref = None
            return commands
        yaw = yaw_of(quat)
        if self.heading_ref is None:
            self.heading_ref = yaw
        err = math.atan2(math.sin(self.heading_ref - yaw), math.cos(self.heading_ref - yaw))
        lim = float(self.cfg.max_command[2])
        return np.array([commands[0], commands[1], min(max(self.cfg.heading_hold * err, -lim), lim)])

    def _loop(self) -> None:
        while self._running:
            try:
                self._iteration()
            except Exception:  # never leave the robot without commands because of a bug: damp
                traceback.print_exc()
                with self._cv:
                    if self.state is not P.BridgeState.DAMPING:
                        try:
                            self._enter(P.BridgeState.DAMPING, P.Fault.INTERNAL_ERROR)
                        except Exception:
                            traceback.print_exc()
                time.sleep(self.dt)

    def _check_stale(self, now: float) -> None:
        """No state for max_state_age, or states whose robot clock does not advance to the
        next deadline (no control step for max_state_age + one period): damping."""
        if self.state not in (P.BridgeState.STANDUP, P.BridgeState.RUNNING):
            return
        age, since_step = now - self._latest_arrival, now - self._last_step
        if age > self.max_state_age or since_step > self.max_state_age + self.dt:
            self.fault_detail = (
                f"newest state {age * 1e3:.1f} ms old (limit {self.max_state_age * 1e3:.1f}), last control step "
                f"{since_step * 1e3:.1f} ms ago (limit {(self.max_state_age + self.dt) * 1e3:.1f})"
            )
            self._enter(P.BridgeState.DAMPING, P.Fault.STALE_STATE)

    def _local_tick(self, now: float) -> None:
        """clock == "local": one control step per absolute deadline of this process's clock,
        from the newest state (fresh by the staleness check)."""
        if self.state is P.BridgeState.WAITING:
            if self._latest is not None and self._latest_arrival > self._waiting_since:
                self._control_step(self._latest, now)  # starts the stand-up
                self._next_tick = now + self.dt
            return
        if self.state in (P.BridgeState.STANDUP, P.BridgeState.RUNNING) and now >= self._next_tick:
            try:
                self._control_step(self._latest, now)
            except Exception:
                traceback.print_exc()
                self._enter(P.BridgeState.DAMPING, P.Fault.INTERNAL_ERROR)
            self._next_tick += self.dt
            if self._next_tick <= now:  # a whole period late: re-anchor instead of bursting
                self._next_tick = now + self.dt

    def _iteration(self) -> None:
        """The supervisor: stale-state check, damping commands, status; sleeps until the next deadline."""
        with self._cv:
            now = time.monotonic()
            self._check_stale(now)
            if self.cfg.clock == "local":
                self._local_tick(now)
            if self.state in (P.BridgeState.DAMPING, P.BridgeState.STOPPED) and now >= self._next_damping:
                self._send_damping()
                self._next_damping += self.dt
                if self._next_damping < now:
                    self._next_damping = now + self.dt
            send_status = now >= self._next_status
            if not send_status:
                deadlines = [self._next_status]
                if self.state in (P.BridgeState.STANDUP, P.BridgeState.RUNNING):
                    deadlines.append(self._latest_arrival + self.max_state_age)
                    deadlines.append(self._last_step + self.max_state_age + self.dt)
                if self.state in (P.BridgeState.DAMPING, P.BridgeState.STOPPED):
                    deadlines.append(self._next_damping)
                if self.cfg.clock == "local" and self.state in (P.BridgeState.STANDUP, P.BridgeState.RUNNING):
                    deadlines.append(self._next_tick)
                if self._running:
                    self._cv.wait(timeout=max(0.0, min(deadlines) - time.monotonic()))
        if send_status:
            self._next_status = now + self.cfg.status_period
            self.publish("status", self.status().encode())

    def start(self) -> None:
        self._running = True
        self._next_status = time.monotonic()
        self._thread = threading.Thread(target=self._loop, name="bridge-control", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        with self._cv:
            self._running = False
            self._cv.notify()
        if self._thread is not None:
            self._thread.join(timeout=2.0)


def warm_up(meta: PolicyMeta, config: BridgeConfig, runner: PolicyRunner) -> Bridge:
    """Run every first-time path of the control step and of the status once, before the
    session opens: a scratch Bridge (sharing `runner`, publishing nowhere) takes a robot
    lying on its side through righting, the stand-up and a few policy steps, with a status
    after every state, then operator commands, a stop, a reset and a stale-state fault.

    A first call can be slow: the first status with step statistics imported numpy.ma
    (np.percentile's lazy import, 15-22 ms) while it held the lock that the next state
    waits on, and that state's command came that much late, or the state went stale."""
    # a staleness limit that these first calls cannot trip (the fault is taken on purpose at the end)
    scratch = Bridge(meta, dataclasses.replace(config, max_state_age=60.0), lambda key, payload: None, runner)
    dt_ns = int(round(meta.control_dt * 1e9))
    states, operator = P.Sender(), P.Sender()
    n = meta.num_joints
    on_side = [math.cos(math.pi / 4), math.sin(math.pi / 4), 0.0, 0.0]  # rolled 90 deg: righting first
    upright = [1.0, 0.0, 0.0, 0.0]
    q = meta.default_joint_pos.astype(np.float64).tolist()

    def state(k: int, quat) -> bytes:
        h = states.next_header()
        h.stamp_ns = k * dt_ns
        return P.RobotState(quat=quat, gyro=[0.0] * 3, q=q, dq=[0.0] * n, header=h).encode()

    def command(flags: int = 0) -> bytes:
        mode = next(iter(scratch.mode_masks)).value
        msg = P.OperatorCommand(vx=0.2, vy=0.0, wz=0.1, propulsion=mode, flags=flags, header=operator.next_header())
        return msg.encode()

    limit = int(60.0 / meta.control_dt)  # a bound: righting + fold + lift take a few seconds of steps
    running = 0
    for k in range(limit):
        scratch.on_state(state(k, on_side if k < 3 else upright))
        scratch.status().encode()
        if k == 5:
            scratch.on_operator(command())
        if scratch.state is P.BridgeState.RUNNING:
            running += 1
            if running > 5:
                break
        elif scratch.state is not P.BridgeState.STANDUP:
            break  # not expected; what ran so far is warm
    status_line(scratch.status())
    scratch.on_operator(command(P.OP_STOP))
    scratch.on_operator(command(P.OP_RESET))
    scratch.on_state(state(limit, upright))  # a new stand-up
    with scratch._cv:
        scratch._check_stale(time.monotonic() + 120.0)  # the stale-state fault and its damping
    scratch.status().encode()
    return scratch  # for a look at what it went through (transitions, notes)


class ZenohBridge:
    """A Bridge wired to a zenoh session: subscribes to state and operator, publishes cmd and status."""

    def __init__(
        self, session, namespace: str, meta: PolicyMeta, config: BridgeConfig, runner=None, trace_steps: int = 0
    ):
        self.session = session
        self.keys = P.keys(namespace)
        self.pubs = {
            "cmd": transport.fast_publisher(session, self.keys["cmd"]),
            "status": session.declare_publisher(self.keys["status"]),
        }
        self.bridge = Bridge(meta, config, self._publish, runner)
        if trace_steps:  # before the subscribers: the first command is traced too
            self.bridge.start_trace(trace_steps)
        self.subs = [
            session.declare_subscriber(self.keys["state"], lambda s: self.bridge.on_state(s.payload.to_bytes())),
            session.declare_subscriber(self.keys["operator"], lambda s: self.bridge.on_operator(s.payload.to_bytes())),
        ]

    def _publish(self, which: str, payload: bytes) -> None:
        self.pubs[which].put(payload)

    def start(self) -> ZenohBridge:
        self.bridge.start()
        return self

    def stop(self) -> None:
        for s in self.subs:  # first: no callback may publish after the publishers are gone
            s.undeclare()
        self.bridge.stop()
        for p in self.pubs.values():
            p.undeclare()


SHIPPED_POLICY = Path(__file__).resolve().parents[2] / "resources" / "policies" / "caster_omni"
"""The trained caster_omni policy the project ships (the default --policy)."""


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument(
        "--policy",
        help="export directory (or its policy.yaml); default: the shipped resources/policies/caster_omni/",
    )
    p.add_argument("--backend", choices=("onnx", "torchscript"), default="onnx")
    p.add_argument(
        "--standup",
        choices=("fold", "linear"),
        default="fold",
        help="fold: fold, tuck and lift with attitude feedback (stands a caster robot up from the floor); "
        "linear: ramp from the measured pose to the default pose",
    )
    p.add_argument("--standup-time", type=float, default=2.0, help="s: the fold stand-up's lift, or the linear ramp")
    p.add_argument(
        "--no-righting",
        action="store_true",
        help="fold stand-up without righting: no keyframes that first roll a robot lying on its back or side "
        "(tilted more than 40 deg) onto its belly, and no watch of the fold (no retries; the policy starts "
        "when the fold ends, however the trunk lies)",
    )
    p.add_argument(
        "--max-tilt-deg",
        type=float,
        default=45.0,
        help="trunk tilt from upright that counts as a fall while the policy runs (damping until reset; 0: off)",
    )
    p.add_argument("--max-state-age-ms", type=float, default=None, help="default: 1.5 control periods")
    p.add_argument("--damping-kd", type=float, default=1.0)
    p.add_argument("--operator-timeout", type=float, default=1.0, help="s; 0 disables")
    p.add_argument("--max-command", type=float, nargs=3, default=(1.0, 1.0, 1.5), metavar=("VX", "VY", "WZ"))
    p.add_argument("--stamp-tolerance-ms", type=float, default=1.0)
    p.add_argument(
        "--heading-hold",
        type=float,
        default=0.0,
        metavar="GAIN",
        help="while told to move with wz 0, command wz = GAIN x the yaw error to the heading at the start of that "
        "command (rad/s per rad; e.g. 2; 0: off, the operator's wz as it is)",
    )
    p.add_argument(
        "--clock",
        choices=("robot", "local"),
        default="robot",
        help="robot: step on the state timestamps (lowest latency); local: on this process's clock, newest state",
    )
    p.add_argument("--duration", type=float, default=0.0, help="stop after this many seconds (0: run until Ctrl-C)")
    p.add_argument(
        "--trace",
        type=Path,
        default=None,
        metavar="CSV",
        help="at exit, write each command's state seq, the state's arrival and the command's send (CLOCK_MONOTONIC "
        f"ns) to CSV: where a state's latency goes (the last {TRACE_STEPS} commands)",
    )
    p.add_argument(
        "--summary-every", type=float, default=10.0, help="seconds between one-line health summaries (0: none)"
    )
    transport.add_zenoh_args(p, role="bridge")
    return p


def status_line(st: P.BridgeStatus) -> str:
    """One line of the bridge's health: state, rate, timing, rejections."""
    rejected = {k: v for k, v in st.rejected_by_reason().items() if v}
    return (
        f"{P.BridgeState(st.state).name}"
        + (f" ({P.Fault(st.fault).name})" if st.fault else "")
        + f", {st.rate_hz:.1f} Hz, period jitter p99 {st.jitter_p99_ms:.2f} ms (max {st.jitter_max_ms:.2f}), "
        f"inference {st.inference_mean_ms:.2f} ms, state age {st.state_age_ms:.1f} ms, "
        f"states {st.received_state}, operator {st.received_operator}, commands {st.commands}, "
        f"rejected {rejected or 'none'}"
    )


def _print_transitions(bridge: Bridge, seen: int) -> int:
    """Print the state changes since `seen` (WAITING -> STANDUP -> RUNNING, faults with
    their reason, stop / reset); returns the new count."""
    changes = list(bridge.transitions)
    for k in range(seen, len(changes)):
        _, state, fault = changes[k]
        before = changes[k - 1][1].name if k else "START"
        reason = f" ({fault.name})" if fault != P.Fault.NONE else ""
        if fault in (P.Fault.STALE_STATE, P.Fault.FALLEN) and bridge.fault_detail:
            reason += f": {bridge.fault_detail}"
        print(f"bridge: {before} -> {state.name}{reason}", flush=True)
    return len(changes)


def _print_notes(bridge: Bridge, seen: int) -> int:
    """Print the bridge's notes since `seen` (e.g. each righting try); returns the new count."""
    notes = list(bridge.notes)
    for note in notes[seen:]:
        print(f"bridge: {note}", flush=True)
    return len(notes)


NO_STATE_HINT_S = 5.0
"""Seconds without any robot state after which the bridge says what to check."""


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.policy is None:
        args.policy = str(SHIPPED_POLICY)
        print(f"bridge: no --policy given: using the shipped policy {args.policy}")
    try:
        transport.check_options(args)  # endpoints and --secure's files, before the slow start-up
    except transport.SessionError as err:
        print(f"bridge: error: {err}", file=sys.stderr)
        return 2
    try:
        meta = load_meta(args.policy)  # fails here, before any zenoh traffic, on an unusable export
    except (PolicyFormatError, FileNotFoundError) as e:
        print(f"bridge: error: {e}", file=sys.stderr)
        return 2
    try:
        cfg = BridgeConfig(
            backend=args.backend,
            standup=args.standup,
            standup_time=args.standup_time,
            righting=not args.no_righting,
            max_tilt_deg=args.max_tilt_deg,
            max_state_age=None if args.max_state_age_ms is None else args.max_state_age_ms / 1e3,
            damping_kd=args.damping_kd,
            operator_timeout=args.operator_timeout,
            max_command=tuple(args.max_command),
            stamp_tolerance=args.stamp_tolerance_ms / 1e3,
            clock=args.clock,
            heading_hold=args.heading_hold,
        )
    except ValueError as e:  # BridgeConfig checks its values
        parser.error(str(e).replace("heading_hold", "--heading-hold"))
    try:
        # Everything slow happens before the session opens and the process goes real-time:
        # the runtime's import, the session's creation and its first runs (under SCHED_FIFO
        # they would hold a core for a few hundred ms; docs/deploy.md, "Timing").
        runner = PolicyRunner(meta, cfg.backend)
    except (PolicyFormatError, FileNotFoundError) as e:
        print(f"bridge: error: {e}", file=sys.stderr)
        return 2
    warm_up(meta, cfg, runner)  # and every first-time path of the control step and the status
    try:
        session = transport.open_session(args)
    except transport.SessionError as err:
        print(f"bridge: error: {err}", file=sys.stderr)
        return 2
    zb = ZenohBridge(session, args.namespace, meta, cfg, runner, TRACE_STEPS if args.trace else 0).start()
    print(
        f"bridge: {meta.task} ({meta.robot}), {1 / meta.control_dt:.0f} Hz, "
        f"keys {zb.keys['state']} -> {zb.keys['cmd']}",
        flush=True,
    )
    seen = 0
    try:
        transport.arm_signals()
        t0 = time.monotonic()
        t_end = t0 + args.duration if args.duration > 0 else float("inf")
        warned = False
        noted, next_summary = 0, t0 + args.summary_every
        while time.monotonic() < t_end:
            time.sleep(min(0.2, max(0.0, t_end - time.monotonic())))
            seen = _print_transitions(zb.bridge, seen)
            noted = _print_notes(zb.bridge, noted)
            if args.summary_every > 0 and time.monotonic() >= next_summary:
                next_summary += args.summary_every
                print(f"bridge: {status_line(zb.bridge.status())}", flush=True)
            if not warned and zb.bridge.received_state == 0 and time.monotonic() - t0 > NO_STATE_HINT_S:
                warned = True
                scouting = "multicast scouting" if args.multicast_scouting else "no endpoint given"
                where = ", ".join(args.connect + args.listen) or scouting
                print(
                    f"bridge: no robot state on {zb.keys['state']} after {NO_STATE_HINT_S:.0f} s: is the robot (or "
                    f"sim_robot) running with --namespace {args.namespace}, and does one side --listen where the "
                    f"other --connect's ({where})?",
                    flush=True,
                )
    except KeyboardInterrupt:
        pass
    finally:
        st = zb.bridge.status()
        zb.stop()
        session.close()
    _print_transitions(zb.bridge, seen)  # a change in the last 0.2 s too (a fault, with what tripped it)
    if args.trace is not None:
        try:
            print(f"bridge: {zb.bridge.write_trace(args.trace)} commands traced to {args.trace}", flush=True)
        except OSError as err:
            print(f"bridge: error: --trace {args.trace}: {err}", file=sys.stderr)
            return 2
    print(
        f"bridge: state {P.BridgeState(st.state).name} ({P.Fault(st.fault).name}), "
        f"policy steps {st.policy_steps}, commands {st.commands}, "
        f"rate {st.rate_hz:.2f} Hz, jitter p99 {st.jitter_p99_ms:.3f} ms, rejected {st.rejected_by_reason()}",
        flush=True,
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
