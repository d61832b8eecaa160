"""A stand-in for the parts of unitree_sdk2py that the fake Go2 and the adapter use, so that
both can run in one process without CycloneDDS: LowState_ / LowCmd_ with the fields of
Unitree's IDL that the project reads or writes (wireless_remote: 40 uint8, as in
unitree_go/msg/dds_/_LowState_.py), and channels that hand each written message to the
topic's subscribers at once, in the writer's thread."""

from __future__ import annotations

from types import SimpleNamespace

from legged_casters.deploy import unitree


def _motor_state():
    return SimpleNamespace(mode=0, q=0.0, dq=0.0)


def _motor_cmd():
    return SimpleNamespace(mode=0, q=0.0, dq=0.0, tau=0.0, kp=0.0, kd=0.0, reserve=[0, 0, 0])


def new_lowstate():
    return SimpleNamespace(
        head=[0, 0],
        level_flag=0,
        tick=0,
        imu_state=SimpleNamespace(quaternion=[1.0, 0.0, 0.0, 0.0], gyroscope=[0.0, 0.0, 0.0]),
        motor_state=[_motor_state() for _ in range(unitree.NUM_MOTORS)],
        wireless_remote=[0] * unitree.WIRELESS_REMOTE_SIZE,
    )


def new_lowcmd():
    return SimpleNamespace(
        head=[0, 0],
        level_flag=0,
        frame_reserve=0,
        sn=[0, 0],
        version=[0, 0],
        bandwidth=0,
        motor_cmd=[_motor_cmd() for _ in range(unitree.NUM_MOTORS)],
        bms_cmd=SimpleNamespace(off=0, reserve=[0, 0, 0]),
        wireless_remote=[0] * unitree.WIRELESS_REMOTE_SIZE,
        led=[0] * 12,
        fan=[0, 0],
        gpio=0,
        reserve=0,
        crc=0,
    )


class Bus:
    """Topics -> subscriber callbacks."""

    def __init__(self):
        self.subs: dict[str, list] = {}

    def sdk(self) -> unitree.Sdk:
        bus = self

        class Publisher:
            def __init__(self, topic, _type):
                self.topic = topic

            def Init(self):  # noqa: N802 - the SDK's name
                pass

            def Write(self, msg):  # noqa: N802
                for cb in list(bus.subs.get(self.topic, ())):
                    cb(msg)

        class Subscriber:
            def __init__(self, topic, _type):
                self.topic = topic

            def Init(self, handler, _depth=10):  # noqa: N802
                bus.subs.setdefault(self.topic, []).append(handler)

            def Close(self):  # noqa: N802
                bus.subs.pop(self.topic, None)

        return unitree.Sdk(
            ChannelFactoryInitialize=lambda *a: None,
            ChannelPublisher=Publisher,
            ChannelSubscriber=Subscriber,
            LowCmd=object,
            LowState=object,
            new_lowcmd=new_lowcmd,
            new_lowstate=new_lowstate,
            reference_crc=None,
        )
