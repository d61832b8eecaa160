"""Unitree's Go2 low-level interface (unitree_sdk2's rt/lowstate and rt/lowcmd), as the
robot-side adapter and the fake Go2 use it.

What lives here:

* `load_sdk()`: imports unitree_sdk2py (the optional extra ``.[unitree]``, which needs
  the CycloneDDS C library; README "Deployment"). The registry's unitree-sdk2 1.0.1
  imports a ``b2`` subpackage that the wheel does not contain (unitreerobotics/
  unitree_sdk2_python issues 36, 73, 81): when that is the only thing missing, an
  empty module stands in for it, and nothing else of the SDK changes.
* `lowcmd_crc()`: the checksum a Go2 verifies before it accepts a LowCmd. The wheel's
  own CRC needs a shared library it does not ship (``utils/lib/crc_amd64.so``), so it is
  computed here: CRC-32 with polynomial 0x04C11DB7, initial value 0xFFFFFFFF, no
  reflection and no final xor (CRC-32/MPEG-2), over the message's C layout read as
  little-endian 32-bit words, each word fed most significant bit first, the last word
  (the crc field itself) excluded. A test checks it against the SDK's pure-Python
  reference implementation.
* `MotorMap`: our joint order (go2.action_layout) <-> Unitree motor indices
  (go2.UNITREE_MOTOR), and the conversions LowState -> (quat, gyro, q, dq) and
  (q, dq, kp, kd) -> LowCmd.
"""

from __future__ import annotations

import importlib.util
import struct
import sys
import types
import zlib
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from legged_casters.robot import go2

LOWSTATE_TOPIC = "rt/lowstate"
LOWCMD_TOPIC = "rt/lowcmd"
NUM_MOTORS = 20
"""Motor slots in a Go2 LowState / LowCmd."""
HEAD = (0xFE, 0xEF)
LEVEL_LOW = 0xFF
MOTOR_SERVO = 0x01
"""motor_cmd[i].mode: 0x01 servo (PD in the motor driver); 0x00 off."""
WIRELESS_REMOTE_SIZE = 40
"""Bytes of LowState.wireless_remote (the Go2 remote's state; deploy/drive.py decodes it)."""
POS_STOP = 2.146e9
VEL_STOP = 16000.0
"""The q / dq values Unitree's examples send to a motor slot they do not drive."""

INSTALL_HINT = (
    "install the Unitree extra: sudo apt-get install cyclonedds-dev (the CycloneDDS C library 0.10.x), "
    "then ./setup.sh unitree (or see README 'Deployment')"
)


class SdkUnavailable(RuntimeError):
    """unitree_sdk2py (or CycloneDDS under it) cannot be imported; the message says how to install it."""


@dataclass
class Sdk:
    ChannelFactoryInitialize: object
    ChannelPublisher: object
    ChannelSubscriber: object
    LowCmd: object
    LowState: object
    new_lowcmd: object
    new_lowstate: object
    reference_crc: object
    """The SDK's own CRC object (its Crc() needs the missing shared library; tests use its
    pure-Python pieces as the reference for ours)."""


_SDK: Sdk | None = None


def load_sdk() -> Sdk:
    global _SDK
    if _SDK is not None:
        return _SDK
    try:
        import cyclonedds  # noqa: F401
    except ImportError as err:
        raise SdkUnavailable(f"CycloneDDS for Python is not installed ({err}); {INSTALL_HINT}") from None
    if "unitree_sdk2py.b2" not in sys.modules:
        spec = importlib.util.find_spec("unitree_sdk2py")
        if spec is None:
            raise SdkUnavailable(f"unitree_sdk2py is not installed; {INSTALL_HINT}")
        b2 = [p for p in spec.submodule_search_locations or [] if (Path(p) / "b2").is_dir()]
        if not b2:  # the 1.0.1 wheel: its __init__ imports a b2 package it does not contain
            sys.modules["unitree_sdk2py.b2"] = types.ModuleType("unitree_sdk2py.b2")
    try:
        from unitree_sdk2py.core.channel import ChannelFactoryInitialize, ChannelPublisher, ChannelSubscriber
        from unitree_sdk2py.idl.default import unitree_go_msg_dds__LowCmd_, unitree_go_msg_dds__LowState_
        from unitree_sdk2py.idl.unitree_go.msg.dds_ import LowCmd_, LowState_
        from unitree_sdk2py.utils.crc import CRC
    except ImportError as err:
        raise SdkUnavailable(f"unitree_sdk2py does not import ({err}); {INSTALL_HINT}") from None
    _SDK = Sdk(
        ChannelFactoryInitialize,
        ChannelPublisher,
        ChannelSubscriber,
        LowCmd_,
        LowState_,
        unitree_go_msg_dds__LowCmd_,
        unitree_go_msg_dds__LowState_,
        CRC,
    )
    return _SDK


# --- CRC -------------------------------------------------------------------------------
_BITREV = bytes(int(f"{b:08b}"[::-1], 2) for b in range(256))
"""Each byte with its bits in reverse order (a bytes.translate table)."""


def _crc32_mpeg2(data: bytes) -> int:
    """CRC-32/MPEG-2 of bytes fed most significant bit first, in C (zlib): the reflected
    CRC-32 that zlib computes, run over the bit-reversed bytes from the same initial value
    and without its final xor, is this CRC's register bit-reversed. About 2 us for a LowCmd's
    words, against 300 us for a table-driven loop in Python, at 500 LowCmds per second on both
    the adapter's and the fake Go2's side."""
    reflected = zlib.crc32(data.translate(_BITREV)) ^ 0xFFFFFFFF
    return int.from_bytes(reflected.to_bytes(4, "little").translate(_BITREV), "big")


def crc32_words(words) -> int:
    """CRC-32/MPEG-2 of 32-bit words, each fed most significant byte (and bit) first."""
    return _crc32_mpeg2(struct.pack(f">{len(words)}I", *words))


# LowCmd_ as the robot's C struct lays it out (4-byte alignment, little-endian).
_LOWCMD_HEAD = "4B" + "4I" + "H2x"  # head[2], level_flag, frame_reserve; sn[2], version[2]; bandwidth
_MOTOR_CMD = "B3x" + "5f" + "3I"  # mode; q, dq, tau, kp, kd; reserve[3]
_LOWCMD_TAIL = "4B" + "40B12B2BB" + "x" + "2I"  # bms_cmd; wireless_remote, led, fan, gpio; reserve, crc
LOWCMD_LAYOUT = struct.Struct("<" + _LOWCMD_HEAD + _MOTOR_CMD * NUM_MOTORS + _LOWCMD_TAIL)


def lowcmd_bytes(cmd) -> bytes:
    values = [*cmd.head, cmd.level_flag, cmd.frame_reserve, *cmd.sn, *cmd.version, cmd.bandwidth]
    for m in cmd.motor_cmd:
        values += [m.mode, m.q, m.dq, m.tau, m.kp, m.kd, *m.reserve]
    values += [cmd.bms_cmd.off, *cmd.bms_cmd.reserve, *cmd.wireless_remote, *cmd.led, *cmd.fan, cmd.gpio]
    values += [cmd.reserve, cmd.crc]
    return LOWCMD_LAYOUT.pack(*values)


def lowcmd_crc(cmd) -> int:
    raw = lowcmd_bytes(cmd)
    words = struct.unpack(f"<{len(raw) // 4}I", raw)
    return crc32_words(words[:-1])


# --- joint mapping ------------------------------------------------------------------------
@dataclass(frozen=True)
class MotorMap:
    """Our joints (action order of `robot`) and the Unitree motor slot of each."""

    robot: str
    joints: tuple[str, ...]
    motors: tuple[int, ...]

    @classmethod
    def for_robot(cls, robot: str) -> MotorMap:
        joints = go2.action_layout(robot).joints
        return cls(robot, joints, tuple(go2.UNITREE_MOTOR[j] for j in joints))

    def __len__(self) -> int:
        return len(self.joints)

    def describe(self) -> str:
        return ", ".join(f"{j.removesuffix('_joint')}->{m}" for j, m in zip(self.joints, self.motors, strict=True))

    def read_state(self, low) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """LowState -> quat (w, x, y, z), gyro (rad/s, body), q, dq in our joint order."""
        imu = low.imu_state
        ms = low.motor_state
        q = np.array([ms[i].q for i in self.motors], dtype=np.float64)
        dq = np.array([ms[i].dq for i in self.motors], dtype=np.float64)
        return np.asarray(imu.quaternion, dtype=np.float64), np.asarray(imu.gyroscope, dtype=np.float64), q, dq

    def write_state(self, low, quat, gyro, q, dq) -> None:
        """Fill a LowState (the fake Go2's side)."""
        low.head = list(HEAD)
        low.level_flag = LEVEL_LOW
        low.imu_state.quaternion = [float(x) for x in quat]
        low.imu_state.gyroscope = [float(x) for x in gyro]
        for k, i in enumerate(self.motors):
            low.motor_state[i].mode = MOTOR_SERVO
            low.motor_state[i].q = float(q[k])
            low.motor_state[i].dq = float(dq[k])

    def write_command(self, cmd, q, dq, kp, kd) -> None:
        """Fill a LowCmd (from a new SDK default one): our joints in servo mode with their
        targets and gains, every other slot off with Unitree's stop values, and the CRC."""
        cmd.head = list(HEAD)
        cmd.level_flag = LEVEL_LOW
        cmd.gpio = 0
        used = set(self.motors)
        for i in range(NUM_MOTORS):
            if i not in used:
                m = cmd.motor_cmd[i]
                m.mode, m.q, m.dq, m.tau, m.kp, m.kd = 0, POS_STOP, VEL_STOP, 0.0, 0.0, 0.0
        for k, i in enumerate(self.motors):
            m = cmd.motor_cmd[i]
            m.mode, m.q, m.dq, m.tau = MOTOR_SERVO, float(q[k]), float(dq[k]), 0.0
            m.kp, m.kd = float(kp[k]), float(kd[k])
        cmd.crc = lowcmd_crc(cmd)

    def read_command(self, cmd) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """LowCmd -> (servo mask, q, dq, kp, kd) in our joint order (the fake Go2's side)."""
        mc = cmd.motor_cmd
        servo = np.array([mc[i].mode == MOTOR_SERVO for i in self.motors])
        arr = [np.array([getattr(mc[i], f) for i in self.motors], dtype=np.float64) for f in ("q", "dq", "kp", "kd")]
        return (servo, *arr)
