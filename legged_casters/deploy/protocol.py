"""The wire protocol between the policy bridge, the robot (or the simulated robot) and the operator.

Every message is one zenoh sample under a robot namespace ``<ns>`` (default ``go2``):

====================  =============  ==========================================
key                   publisher      payload
====================  =============  ==========================================
``<ns>/state``        robot          :class:`RobotState`
``<ns>/cmd``          bridge         :class:`JointCommand`
``<ns>/operator``     operator       :class:`OperatorCommand`
``<ns>/status``       bridge         :class:`BridgeStatus`
``<ns>/sim/truth``    sim robot      :class:`SimTruth` (simulation only; tests and logging)
====================  =============  ==========================================

Payloads are little-endian ``struct`` records with a common 20-byte header::

    magic u16 (0x434C, "LC")  version u8  type u8  epoch u32  seq u32  stamp_ns u64

``epoch`` is a random number a sender draws when it starts, ``seq`` counts that
sender's messages from 0 and ``stamp_ns`` is the sender's steady (monotonic) clock in
nanoseconds. All floats are float32. Joint arrays hold ``n`` values (the count is in
the message) in the policy's joint order, ``legged_casters.robot.go2.action_layout``:
12 for the caster and point-foot Go2 (FL, FR, RL, RR x hip, thigh, calf), 16 for the
driving-wheel Go2 (the 12 leg joints, then the FL, FR, RL, RR wheels).

Version 2 (this one) carries ``n`` in the state and command messages and adds a
velocity target ``dq`` to the command, so that a wheel runs as a velocity servo
(kp 0, dq target, kd), as on a Go2-W LowCmd. Version 1 had 12 joints and no ``dq``.

Decoding checks the exact length, magic, version and type, that every float is
finite and that the values are in range (pad bytes are written as zeros and never
read); a failure raises :class:`ProtocolError` whose ``reason`` is one of
:data:`REJECT_REASONS`. :class:`SequenceFilter` rejects replayed and out-of-order
messages; :class:`OperatorFilter` does the same for the operator stream without letting
one message lock the operator out. Nothing here touches zenoh.
"""

from __future__ import annotations

import enum
import math
import os
import struct
from dataclasses import dataclass, field

MAGIC = 0x434C
VERSION = 2
NUM_JOINTS = 12
"""Joints of the caster and point-foot Go2 (the default of the encoders' callers)."""
MAX_JOINTS = 32

HEADER = struct.Struct("<HBBIIQ")
HEADER_SIZE = HEADER.size  # 20


class MsgType(enum.IntEnum):
    STATE = 1
    COMMAND = 2
    OPERATOR = 3
    STATUS = 4
    SIM_TRUTH = 5


class CommandMode(enum.IntEnum):
    """What a joint command asks the robot to do (also what the robot reports it is doing)."""

    NONE = 0  # robot side only: no command received yet
    POLICY = 1  # track the policy's targets with the given gains
    DAMPING = 2  # kp = 0, small kd: a soft, passive stance
    STANDUP = 3  # the bridge's ramp from the measured pose to the default pose
    HOLD = 4  # robot side only: holding its start pose before the first command


class PropulsionMode(enum.IntEnum):
    """Operator propulsion modes; the bridge maps the name to the export's mask."""

    FOUR_WHEEL = 0
    FRONT_WHEEL = 1
    REAR_WHEEL = 2

    @property
    def key(self) -> str:
        return self.name.lower()


class BridgeState(enum.IntEnum):
    WAITING = 0  # no valid robot state yet: nothing is published
    STANDUP = 1  # standing up from the measured pose to the default pose
    RUNNING = 2  # policy in control
    DAMPING = 3  # fault (stale state, non-finite policy output, fallen): damping until reset
    STOPPED = 4  # operator stop latched: damping until reset


class Fault(enum.IntEnum):
    NONE = 0
    STALE_STATE = 1
    NONFINITE_ACTION = 2
    OPERATOR_STOP = 3
    INTERNAL_ERROR = 4  # an unexpected exception in the control loop
    FALLEN = 5  # the trunk tilted beyond the bridge's --max-tilt-deg while the policy ran


REJECT_REASONS: tuple[str, ...] = ("malformed", "version", "nonfinite", "out_of_range", "out_of_order")
"""Why a message was rejected; the index is the position in BridgeStatus.rejected."""


class ProtocolError(ValueError):
    """A payload that must not be used. ``reason`` is one of REJECT_REASONS."""

    def __init__(self, reason: str, message: str):
        if reason not in REJECT_REASONS:
            raise ValueError(f"unknown reject reason {reason!r}")
        super().__init__(f"{reason}: {message}")
        self.reason = reason


def new_epoch() -> int:
    """A random non-zero sender epoch."""
    return int.from_bytes(os.urandom(4), "little") or 1


@dataclass
class Header:
    epoch: int = 0
    seq: int = 0
    stamp_ns: int = 0


def _check_finite(values, what: str) -> None:
    for v in values:
        if not math.isfinite(v):
            raise ProtocolError("nonfinite", f"{what} contains {v}")


def _decode_header(buf: bytes, mtype: MsgType, size: int | None) -> Header:
    if not isinstance(buf, bytes | bytearray | memoryview):
        raise ProtocolError("malformed", f"payload is {type(buf).__name__}, not bytes")
    if len(buf) < HEADER_SIZE:
        raise ProtocolError("malformed", f"{len(buf)} bytes is shorter than the {HEADER_SIZE}-byte header")
    magic, version, t, epoch, seq, stamp = HEADER.unpack_from(buf, 0)
    if magic != MAGIC:
        raise ProtocolError("malformed", f"bad magic 0x{magic:04x}")
    if version != VERSION:
        raise ProtocolError("version", f"version {version}, this build speaks {VERSION}")
    if t != mtype:
        raise ProtocolError("malformed", f"message type {t}, expected {int(mtype)} ({mtype.name})")
    if size is not None and len(buf) != size:
        raise ProtocolError("malformed", f"{mtype.name} must be {size} bytes, got {len(buf)}")
    return Header(epoch, seq, stamp)


def _pack_header(mtype: MsgType, h: Header) -> bytes:
    return HEADER.pack(MAGIC, VERSION, int(mtype), h.epoch & 0xFFFFFFFF, h.seq & 0xFFFFFFFF, h.stamp_ns)


def _floats(values, n: int, what: str) -> list[float]:
    out = [float(v) for v in values]
    if len(out) != n:
        raise ValueError(f"{what} needs {n} values, got {len(out)}")
    return out


# --- robot state -------------------------------------------------------------------------
_STATE_HEAD = struct.Struct("<BBBx4f3f")


def _joint_count(n: int, what: str) -> int:
    if not 1 <= n <= MAX_JOINTS:
        raise ProtocolError("malformed", f"{what} has {n} joints (1..{MAX_JOINTS})")
    return n


def _decode_sized(buf: bytes, mtype: MsgType, head: struct.Struct, count_at: int, arrays: int) -> tuple[Header, int]:
    """Header + joint count of a message whose body is `head` then `arrays` float arrays of n."""
    _decode_header(buf, mtype, None)  # magic, version, type first
    if len(buf) < HEADER_SIZE + head.size:
        raise ProtocolError("malformed", f"{mtype.name} of {len(buf)} bytes is shorter than its fixed part")
    n = _joint_count(buf[HEADER_SIZE + count_at], mtype.name)
    return _decode_header(buf, mtype, HEADER_SIZE + head.size + 4 * arrays * n), n


@dataclass
class RobotState:
    """Robot -> bridge: what a Go2 LowState carries that the policy needs.

    quat: IMU orientation (w, x, y, z), trunk to world; gyro: IMU angular velocity in
    the trunk frame (rad/s); q / dq: joint angles (rad) and velocities (rad/s), n of
    each; robot_mode: the CommandMode the robot is applying (NONE, HOLD or DAMPING when
    its own watchdog fired); flags: no bits defined, must be 0 (anything else is rejected).
    """

    quat: list[float]
    gyro: list[float]
    q: list[float]
    dq: list[float]
    robot_mode: int = CommandMode.NONE
    flags: int = 0
    header: Header = field(default_factory=Header)

    @staticmethod
    def size(n: int = NUM_JOINTS) -> int:
        return HEADER_SIZE + _STATE_HEAD.size + 8 * n

    def encode(self) -> bytes:
        n = len(self.q)
        body = _STATE_HEAD.pack(
            int(self.robot_mode), int(self.flags), n, *_floats(self.quat, 4, "quat"), *_floats(self.gyro, 3, "gyro")
        )
        arrays = struct.pack(f"<{2 * n}f", *_floats(self.q, n, "q"), *_floats(self.dq, n, "dq"))
        return _pack_header(MsgType.STATE, self.header) + body + arrays

    @classmethod
    def decode(cls, buf: bytes) -> RobotState:
        h, n = _decode_sized(buf, MsgType.STATE, _STATE_HEAD, 2, 2)
        v = _STATE_HEAD.unpack_from(buf, HEADER_SIZE)
        mode, flags, floats = v[0], v[1], v[3:]
        joints = struct.unpack_from(f"<{2 * n}f", buf, HEADER_SIZE + _STATE_HEAD.size)
        _check_finite(floats + joints, "state")
        if mode not in CommandMode._value2member_map_:
            raise ProtocolError("out_of_range", f"robot_mode {mode}")
        if flags:
            raise ProtocolError("out_of_range", f"state flags {flags:#04x}: no flag bits are defined (send 0)")
        quat = list(floats[0:4])
        norm = math.sqrt(sum(x * x for x in quat))
        if abs(norm - 1.0) > 0.05:
            raise ProtocolError("out_of_range", f"quaternion norm {norm:.4f} is not 1")
        return cls(
            quat=quat,
            gyro=list(floats[4:7]),
            q=list(joints[:n]),
            dq=list(joints[n:]),
            robot_mode=mode,
            flags=flags,
            header=h,
        )


# --- joint command -----------------------------------------------------------------------
_CMD_HEAD = struct.Struct("<BBxxI")
NO_STATE_SEQ = 0xFFFFFFFF
"""JointCommand.state_seq of a command that answers no state (e.g. damping on a timer)."""


@dataclass
class JointCommand:
    """Bridge -> robot: per-joint targets and gains, like a Go2 LowCmd's motor_cmd[i]
    q / dq / kp / kd.

    The robot applies tau = kp (q_target - q) + kd (dq_target - dq), clipped to its
    torque limits: a leg joint is a position servo (dq_target 0), a wheel a velocity
    servo (kp 0). mode: CommandMode (POLICY, DAMPING, STANDUP); state_seq: seq of the
    RobotState the command was computed from (0xFFFFFFFF when none, e.g. damping on a
    timer). dq None: zeros.
    """

    mode: int
    q: list[float]
    kp: list[float]
    kd: list[float]
    state_seq: int = NO_STATE_SEQ
    header: Header = field(default_factory=Header)
    dq: list[float] | None = None

    @staticmethod
    def size(n: int = NUM_JOINTS) -> int:
        return HEADER_SIZE + _CMD_HEAD.size + 16 * n

    def encode(self) -> bytes:
        n = len(self.q)
        q = _floats(self.q, n, "q")
        dq = _floats(self.dq if self.dq is not None else [0.0] * n, n, "dq")
        kp = _floats(self.kp, n, "kp")
        kd = _floats(self.kd, n, "kd")
        for v in q + dq + kp + kd:
            if not math.isfinite(v):
                raise ValueError("refusing to encode a joint command with non-finite values")
        return (
            _pack_header(MsgType.COMMAND, self.header)
            + _CMD_HEAD.pack(int(self.mode), _joint_count(n, "command"), self.state_seq & 0xFFFFFFFF)
            + struct.pack(f"<{4 * n}f", *q, *dq, *kp, *kd)
        )

    @classmethod
    def decode(cls, buf: bytes) -> JointCommand:
        h, n = _decode_sized(buf, MsgType.COMMAND, _CMD_HEAD, 1, 4)
        mode, _, state_seq = _CMD_HEAD.unpack_from(buf, HEADER_SIZE)
        floats = struct.unpack_from(f"<{4 * n}f", buf, HEADER_SIZE + _CMD_HEAD.size)
        _check_finite(floats, "command")
        if mode not in (CommandMode.POLICY, CommandMode.DAMPING, CommandMode.STANDUP):
            raise ProtocolError("out_of_range", f"command mode {mode}")
        q, dq = list(floats[:n]), list(floats[n : 2 * n])
        kp, kd = list(floats[2 * n : 3 * n]), list(floats[3 * n :])
        if min(kp) < 0.0 or min(kd) < 0.0:
            raise ProtocolError("out_of_range", "negative gain")
        return cls(mode=mode, q=q, kp=kp, kd=kd, state_seq=state_seq, header=h, dq=dq)


# --- operator ----------------------------------------------------------------------------
_OP_BODY = struct.Struct("<3fBBxx")
OP_STOP = 0x01
OP_RESET = 0x02


@dataclass
class OperatorCommand:
    """Operator -> bridge: velocity command (vx, vy m/s, wz rad/s, trunk frame),
    propulsion mode and the stop / reset flags (bit 0 stop, bit 1 reset).

    A stop latches in the bridge until a message with the reset flag (and without the
    stop flag) arrives."""

    vx: float = 0.0
    vy: float = 0.0
    wz: float = 0.0
    propulsion: int = PropulsionMode.FOUR_WHEEL
    flags: int = 0
    header: Header = field(default_factory=Header)

    SIZE = HEADER_SIZE + _OP_BODY.size

    @property
    def stop(self) -> bool:
        return bool(self.flags & OP_STOP)

    @property
    def reset(self) -> bool:
        return bool(self.flags & OP_RESET)

    def encode(self) -> bytes:
        return _pack_header(MsgType.OPERATOR, self.header) + _OP_BODY.pack(
            float(self.vx), float(self.vy), float(self.wz), int(self.propulsion), int(self.flags)
        )

    @classmethod
    def decode(cls, buf: bytes) -> OperatorCommand:
        h = _decode_header(buf, MsgType.OPERATOR, cls.SIZE)
        vx, vy, wz, prop, flags = _OP_BODY.unpack_from(buf, HEADER_SIZE)
        _check_finite((vx, vy, wz), "operator command")
        if prop not in PropulsionMode._value2member_map_:
            raise ProtocolError("out_of_range", f"propulsion mode {prop}")
        if flags & ~(OP_STOP | OP_RESET):
            raise ProtocolError("out_of_range", f"unknown operator flags 0x{flags:02x}")
        return cls(vx, vy, wz, prop, flags, h)


# --- bridge status -----------------------------------------------------------------------
_N_REASONS = len(REJECT_REASONS)
_STATUS_BODY = struct.Struct(f"<BBxx{_N_REASONS}I5I2Q6f")


@dataclass
class BridgeStatus:
    """Bridge -> anyone: its state machine, counters and control-rate statistics.

    rejected: one counter per REJECT_REASONS entry (all topics together);
    last_state_seq / last_operator_seq: last accepted seqs; last_cmd_seq: seq of the
    last published command; received_state / received_operator: accepted messages;
    commands / policy_steps: published commands, policy evaluations; rate_hz: achieved
    policy rate over the last window; period_mean_ms / jitter_p99_ms / jitter_max_ms:
    policy step period and its deviation from control_dt; inference_mean_ms;
    state_age_ms: age of the newest state when the status was made.
    """

    state: int = BridgeState.WAITING
    fault: int = Fault.NONE
    rejected: list[int] = field(default_factory=lambda: [0] * _N_REASONS)
    last_state_seq: int = 0
    last_operator_seq: int = 0
    last_cmd_seq: int = 0
    received_state: int = 0
    received_operator: int = 0
    commands: int = 0
    policy_steps: int = 0
    rate_hz: float = 0.0
    period_mean_ms: float = 0.0
    jitter_p99_ms: float = 0.0
    jitter_max_ms: float = 0.0
    inference_mean_ms: float = 0.0
    state_age_ms: float = 0.0
    header: Header = field(default_factory=Header)

    SIZE = HEADER_SIZE + _STATUS_BODY.size

    def rejected_by_reason(self) -> dict[str, int]:
        return dict(zip(REJECT_REASONS, self.rejected, strict=True))

    def encode(self) -> bytes:
        return _pack_header(MsgType.STATUS, self.header) + _STATUS_BODY.pack(
            int(self.state),
            int(self.fault),
            *[min(int(c), 0xFFFFFFFF) for c in self.rejected],
            self.last_state_seq & 0xFFFFFFFF,
            self.last_operator_seq & 0xFFFFFFFF,
            self.last_cmd_seq & 0xFFFFFFFF,
            min(self.received_state, 0xFFFFFFFF),
            min(self.received_operator, 0xFFFFFFFF),
            self.commands,
            self.policy_steps,
            self.rate_hz,
            self.period_mean_ms,
            self.jitter_p99_ms,
            self.jitter_max_ms,
            self.inference_mean_ms,
            min(self.state_age_ms, 3.0e38),
        )

    @classmethod
    def decode(cls, buf: bytes) -> BridgeStatus:
        h = _decode_header(buf, MsgType.STATUS, cls.SIZE)
        v = _STATUS_BODY.unpack_from(buf, HEADER_SIZE)
        _check_finite(v[-6:], "status")
        state, fault = v[0], v[1]
        if state not in BridgeState._value2member_map_ or fault not in Fault._value2member_map_:
            raise ProtocolError("out_of_range", f"bridge state {state} / fault {fault}")
        r = list(v[2 : 2 + _N_REASONS])
        rest = v[2 + _N_REASONS :]
        return cls(state, fault, r, *rest, header=h)


# --- simulation truth --------------------------------------------------------------------
_TRUTH_BODY = struct.Struct("<d3f3f")


@dataclass
class SimTruth:
    """Sim robot -> tests: simulation time (s), trunk position (m) and linear velocity
    (m/s) in the world frame. No real robot publishes this."""

    sim_time: float
    pos: list[float]
    lin_vel: list[float]
    header: Header = field(default_factory=Header)

    SIZE = HEADER_SIZE + _TRUTH_BODY.size

    def encode(self) -> bytes:
        return _pack_header(MsgType.SIM_TRUTH, self.header) + _TRUTH_BODY.pack(
            float(self.sim_time), *_floats(self.pos, 3, "pos"), *_floats(self.lin_vel, 3, "lin_vel")
        )

    @classmethod
    def decode(cls, buf: bytes) -> SimTruth:
        h = _decode_header(buf, MsgType.SIM_TRUTH, cls.SIZE)
        v = _TRUTH_BODY.unpack_from(buf, HEADER_SIZE)
        _check_finite(v, "truth")
        return cls(v[0], list(v[1:4]), list(v[4:7]), h)


# --- sequence checking -------------------------------------------------------------------
class SequenceFilter:
    """Accept each sender's messages only in increasing seq order.

    A message from the current epoch must have a larger seq than the last accepted one
    (a replay or a late, reordered message is rejected). A new epoch (the sender
    restarted) is accepted whatever its first seq and replaces the current one;
    messages from an epoch seen before and replaced are rejected for good, so a replay
    of an old session cannot take over.

    Within an epoch a message may skip at most `window` sequence numbers (lost
    messages); one that jumps further ahead is rejected and changes nothing. A message
    that jumps ahead by up to `window` is accepted, and the real stream behind it is then
    out of order until it passes that seq: the receiver decides when to give up on the
    old anchor with :meth:`reanchor` (the bridge does on an operator reset, and limits
    the state window to what the staleness limit allows). The default window, 65536
    messages, is over two minutes of a 500 Hz stream."""

    WINDOW = 1 << 16

    def __init__(self, max_retired: int = 64, window: int = WINDOW):
        if window < 1:
            raise ValueError(f"window must be >= 1, got {window}")
        self.epoch: int | None = None
        self.last_seq = -1
        self._retired: list[int] = []
        self._max_retired = max_retired
        self.window = window
        self._anchor = False

    def reanchor(self) -> None:
        """Accept the next message of the current epoch whatever its seq (ahead, behind or
        equal), and count on from it. Replaced epochs stay rejected."""
        self._anchor = True

    def check(self, h: Header) -> None:
        """Raise ProtocolError('out_of_order') or record h as the newest message."""
        if h.epoch == self.epoch:
            if not self._anchor:
                if h.seq <= self.last_seq:
                    raise ProtocolError("out_of_order", f"seq {h.seq} after {self.last_seq}")
                if h.seq - self.last_seq > self.window:
                    raise ProtocolError(
                        "out_of_order", f"seq {h.seq} jumps more than {self.window} past {self.last_seq}"
                    )
        else:
            if h.epoch in self._retired:
                raise ProtocolError("out_of_order", f"epoch {h.epoch:#x} was replaced by a newer sender")
            if self.epoch is not None:
                self._retired.append(self.epoch)
                del self._retired[: -self._max_retired]
            self.epoch = h.epoch
        self.last_seq = h.seq
        self._anchor = False


class OperatorFilter:
    """The operator stream's sequence rule: replays are rejected, but no single message,
    whatever its epoch and seq, can lock the operator's later messages out.

    Within the current epoch a message up to `window` seqs ahead of the highest accepted
    one is accepted and becomes the highest; one fewer than `window` behind it is
    accepted once if that seq has not been accepted before (a bitmap of the last `window`
    seqs, as in the IPsec / DTLS anti-replay window). So a message that jumped ahead by up
    to `window` leaves the real stream behind it accepted, and the real stream passes it
    within `window` messages. Anything older, or seen before, is rejected (a replay).

    A message further ahead, or from another epoch, is not accepted on its own: it is
    held as a candidate, and the stream moves to it only when the next message that is
    not accepted continues it (same epoch, seq up to `window` past the candidate's); an
    accepted message of the current stream in between drops the candidate. A restarted
    operator (a new epoch) or one whose stream lost more than `window` messages is then
    followed from its second message; a single corrupt, forged or replayed message
    changes nothing the real stream depends on. Epochs that were replaced stay rejected.
    The first epoch the filter sees is accepted at once.

    Stops do not depend on this filter: the bridge acts on every valid stop, in order or
    not (stopping is always safe)."""

    WINDOW = 64

    def __init__(self, window: int = WINDOW, max_retired: int = 64):
        if window < 1:
            raise ValueError(f"window must be >= 1, got {window}")
        self.window = window
        self.epoch: int | None = None
        self.last_seq = -1
        self._seen = 0  # bit k: seq last_seq - k was accepted (k < window)
        self._candidate: tuple[int, int] | None = None
        self._retired: list[int] = []
        self._max_retired = max_retired

    def _adopt(self, h: Header) -> None:
        if self.epoch is not None and h.epoch != self.epoch:
            self._retired.append(self.epoch)
            del self._retired[: -self._max_retired]
        self.epoch, self.last_seq, self._seen = h.epoch, h.seq, 1
        self._candidate = None

    def check(self, h: Header) -> None:
        """Raise ProtocolError('out_of_order') or record h as accepted."""
        if self.epoch is None:
            self._adopt(h)
            return
        if h.epoch == self.epoch:
            d = h.seq - self.last_seq
            if 0 < d <= self.window:
                self._seen = ((self._seen << d) | 1) & ((1 << self.window) - 1)
                self.last_seq = h.seq
                self._candidate = None  # the stream goes on where it was: forget a held jump
                return
            if -self.window < d <= 0:
                if (self._seen >> -d) & 1:
                    raise ProtocolError("out_of_order", f"seq {h.seq} was accepted before (a replay)")
                self._seen |= 1 << -d
                self._candidate = None
                return
            if d <= -self.window:
                raise ProtocolError(
                    "out_of_order", f"seq {h.seq} is {self.window} or more behind {self.last_seq} (a replay)"
                )
        elif h.epoch in self._retired:
            raise ProtocolError("out_of_order", f"epoch {h.epoch:#x} was replaced by a newer sender")
        c = self._candidate
        if c is not None and c[0] == h.epoch and 0 < h.seq - c[1] <= self.window:
            self._adopt(h)  # a second message continues the jump: follow the stream there
            return
        self._candidate = (h.epoch, h.seq)
        where = "a new epoch" if h.epoch != self.epoch else f"more than {self.window} past {self.last_seq}"
        raise ProtocolError("out_of_order", f"seq {h.seq} is {where}: held until the next message continues it")


class Sender:
    """Stamps outgoing messages of one sender: fixed epoch, seq counting from 0."""

    def __init__(self, clock_ns=None):
        import time

        self.epoch = new_epoch()
        self.seq = 0
        self._clock = clock_ns or time.monotonic_ns

    def next_header(self) -> Header:
        if self.seq > 0xFFFFFFFF:  # after 2^32 messages: continue as a new sender
            self.epoch, self.seq = new_epoch(), 0
        h = Header(self.epoch, self.seq, self._clock())
        self.seq += 1
        return h


class RoundTrip:
    """Robot side: the time from publishing a state to receiving the command computed
    from it (matched by the command's `state_seq`). Thread-safe."""

    def __init__(self, keep: int = 2000):
        import threading

        self._lock = threading.Lock()
        self._sent: dict[int, float] = {}
        self._keep = keep
        self._samples: list[float] = []

    def sent(self, seq: int, t: float) -> None:
        with self._lock:
            self._sent[seq] = t
            if len(self._sent) > self._keep:
                for old in list(self._sent)[: self._keep // 2]:
                    del self._sent[old]

    def answered(self, state_seq: int, t: float) -> None:
        with self._lock:
            sent = self._sent.pop(state_seq, None)
            if sent is not None:
                self._samples.append(t - sent)

    def take(self) -> list[float]:
        """The round trips (s) since the last call."""
        with self._lock:
            out, self._samples = self._samples, []
        return out

    def summary(self) -> str:
        """'latency p50 X / p99 Y ms' over the round trips since the last call."""
        lat = [1e3 * x for x in self.take()]
        if not lat:
            return "latency -"
        lat.sort()
        pick = lambda q: lat[min(len(lat) - 1, int(q * len(lat)))]  # noqa: E731
        return f"latency p50 {pick(0.5):.1f} / p99 {pick(0.99):.1f} ms"


def keys(namespace: str) -> dict[str, str]:
    """The zenoh key expressions of a robot namespace."""
    ns = namespace.strip("/")
    if not ns or any(c in ns for c in "*$#?"):
        raise ValueError(f"invalid robot namespace {namespace!r}")
    return {
        "state": f"{ns}/state",
        "cmd": f"{ns}/cmd",
        "operator": f"{ns}/operator",
        "status": f"{ns}/status",
        "truth": f"{ns}/sim/truth",
    }
