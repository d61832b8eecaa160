"""Read an exported policy (policy.yaml + policy.onnx / policy.pt) and build its observation.

Only the export's files are used: no training code or config. The observation is
built exactly as the training env builds it (``legged_casters/envs/base.py``):
each term's raw value times its scale, concatenated in the listed order, clipped to
``observation.clip``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import yaml

from legged_casters.robot import go2

FORMAT_VERSION = 1

JOINT_TERMS = ("joint_pos", "joint_vel", "actions")
"""Terms with one value per actuated joint (12 or 16 by robot)."""


def term_dims(num_joints: int = 12) -> dict[str, int]:
    """Observation terms the bridge can build from robot state + operator input, with
    their sizes for a robot with `num_joints` actuated joints."""
    return {
        "commands": 3,
        "mode_mask": 4,
        "ang_vel": 3,
        "projected_gravity": 3,
        **dict.fromkeys(JOINT_TERMS, num_joints),
        "gait_phase": 2,
    }


TERM_DIMS: dict[str, int] = term_dims()
"""term_dims of the 12-joint robots."""
HISTORY_TERM = "proprio_history"
"""A stack of earlier steps' terms (policy.yaml `history`: length, terms, newest first)."""

UNMEASURABLE: dict[str, str] = {
    "base_lin_vel": "the trunk's linear velocity is privileged simulator state; a real Go2 does not measure it "
    "(the go2_flat baseline observes it, so its export cannot be deployed with this bridge)",
    "lin_vel": "the trunk's world-frame linear velocity is privileged simulator state",
    "base_height": "the trunk height above the floor is privileged simulator state",
}


class PolicyFormatError(ValueError):
    """policy.yaml does not describe a policy this bridge can run."""


@dataclass
class PolicyMeta:
    directory: Path
    task: str
    robot: str
    joint_names: list[str]
    default_joint_pos: np.ndarray
    action_scale: float
    clip_actions: float
    kp: np.ndarray
    kd: np.ndarray
    torque_limits: np.ndarray
    joint_pos_limits: np.ndarray
    """(n, 2) target limits: rad for position joints, rad/s for velocity joints."""
    control_dt: float
    physics_dt: float
    obs_dim: int
    obs_clip: float
    obs_terms: list[tuple[str, int, float]]
    propulsion_modes: dict[str, list[float]]
    files: dict[str, str]
    onnx_input: str
    onnx_output: str
    history_length: int = 0
    history_terms: tuple[str, ...] = ()
    gait_frequency: float = 0.0
    """Hz of the clock behind the gait_phase term (policy.yaml gait_clock.frequency); 0: none."""
    joint_control: tuple[str, ...] = ()
    """Per joint: "position" (target default + action_scale * action, rad) or "velocity"
    (target velocity_action_scale * action, rad/s, kp 0). Empty: all position (older exports)."""
    velocity_action_scale: float = 0.0

    @property
    def num_joints(self) -> int:
        return len(self.joint_names)

    @property
    def position_mask(self) -> np.ndarray:
        control = self.joint_control or (go2.CONTROL_POSITION,) * self.num_joints
        return np.array([c == go2.CONTROL_POSITION for c in control])

    def targets(self, actions: np.ndarray, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(q_target, dq_target) of clipped policy actions: position joints get
        default + action_scale * action and dq 0; velocity joints hold q (kp is 0)
        and get dq velocity_action_scale * action; both clipped to joint_pos_limits."""
        pos = self.position_mask
        lo, hi = self.joint_pos_limits[:, 0], self.joint_pos_limits[:, 1]
        q_t = np.where(pos, np.clip(self.default_joint_pos + self.action_scale * actions, lo, hi), q)
        dq_t = np.where(pos, 0.0, np.clip(self.velocity_action_scale * actions, lo, hi))
        return q_t, dq_t


def _vec(d: dict, key: str, n: int) -> np.ndarray:
    if key not in d:
        raise PolicyFormatError(f"policy.yaml: missing {key!r}")
    arr = np.asarray(d[key], dtype=np.float64)
    if arr.shape != (n,) or not np.all(np.isfinite(arr)):
        raise PolicyFormatError(f"policy.yaml: {key} must be {n} finite numbers, got {d[key]!r}")
    return arr


def _num(d: dict, key: str, positive: bool = True) -> float:
    if key not in d:
        raise PolicyFormatError(f"policy.yaml: missing {key!r}")
    v = float(d[key])
    if not math.isfinite(v) or (positive and v <= 0):
        raise PolicyFormatError(f"policy.yaml: {key} must be a {'positive ' if positive else ''}number, got {v}")
    return v


def load_meta(path: str | Path) -> PolicyMeta:
    """Parse and check policy.yaml (`path` is the file or the export directory)."""
    path = Path(path)
    if path.is_dir():
        path = path / "policy.yaml"
    if not path.is_file():
        raise FileNotFoundError(f"no policy metadata at {path}")
    d = yaml.safe_load(path.read_text())
    if not isinstance(d, dict):
        raise PolicyFormatError(f"{path}: not a YAML mapping")
    if d.get("format_version") != FORMAT_VERSION:
        raise PolicyFormatError(f"{path}: format_version {d.get('format_version')!r}, expected {FORMAT_VERSION}")
    robot = str(d.get("robot", "caster"))
    try:
        layout = go2.action_layout(robot)
    except ValueError:
        raise PolicyFormatError(f"{path}: unknown robot {robot!r}; expected 'caster', 'point' or 'wheel'") from None
    names = list(d.get("joint_names") or [])
    if names != list(layout.joints):
        raise PolicyFormatError(
            f"{path}: joint_names {names} differ from the {robot} robot's joint order {list(layout.joints)}"
        )
    n = len(names)
    control = tuple(str(c) for c in (d.get("joint_control") or (go2.CONTROL_POSITION,) * n))
    if control != layout.control:
        raise PolicyFormatError(
            f"{path}: joint_control {list(control)} differs from the {robot} robot's {list(layout.control)}"
        )
    lims = np.asarray(d.get("joint_pos_limits"), dtype=np.float64)
    if lims.shape != (n, 2) or not np.all(np.isfinite(lims)) or np.any(lims[:, 0] >= lims[:, 1]):
        raise PolicyFormatError(f"{path}: joint_pos_limits must be {n} [lo, hi] pairs with lo < hi")
    dims = term_dims(n)  # this robot's term sizes
    obs = d.get("observation") or {}
    terms = []
    for t in obs.get("terms") or []:
        name, dim, scale = t.get("name"), int(t.get("dim", -1)), float(t.get("scale", 1.0))
        if name in UNMEASURABLE:
            raise PolicyFormatError(
                f"{path}: observation term {name!r} cannot be deployed: {UNMEASURABLE[name]}. "
                f"Known terms: {sorted(dims)}"
            )
        if name == HISTORY_TERM:
            terms.append((name, dim, scale))
            continue
        if name not in dims:
            raise PolicyFormatError(
                f"{path}: unknown observation term {name!r}; the bridge can build {sorted([*dims, HISTORY_TERM])}"
            )
        if dim != dims[name]:
            raise PolicyFormatError(f"{path}: term {name!r} has dim {dim}, the bridge builds {dims[name]}")
        if not math.isfinite(scale):
            raise PolicyFormatError(f"{path}: term {name!r} has scale {scale}")
        terms.append((name, dim, scale))
    if not terms:
        raise PolicyFormatError(f"{path}: observation.terms is empty")
    obs_dim = int(obs.get("dim", -1))
    if obs_dim != sum(t[1] for t in terms):
        raise PolicyFormatError(f"{path}: observation.dim {obs_dim} != sum of term dims {sum(t[1] for t in terms)}")
    modes = {str(k): [float(x) for x in v] for k, v in (d.get("propulsion_modes") or {}).items()}
    if any(len(v) != 4 for v in modes.values()):
        raise PolicyFormatError(f"{path}: propulsion_modes masks must have 4 values")
    if any(t[0] == "mode_mask" for t in terms) and not modes:
        raise PolicyFormatError(f"{path}: the policy observes mode_mask but propulsion_modes is empty")
    hist = d.get("history") or {}
    history_length, history_terms = 0, ()
    if any(t[0] == HISTORY_TERM for t in terms):
        try:
            history_terms = tuple(str(t) for t in (hist.get("terms") or ())) if isinstance(hist, dict) else ()
            history_length = int(hist.get("length", 0)) if isinstance(hist, dict) else 0
        except (TypeError, ValueError):
            history_terms, history_length = (), 0
        scaled = {t[0] for t in terms}
        bad = [t for t in history_terms if t not in dims or t not in scaled]
        if history_length < 1 or not history_terms or bad:
            raise PolicyFormatError(
                f"{path}: the policy observes {HISTORY_TERM} but `history` does not say how to build it "
                f"(length >= 1 and terms that the policy also observes directly; got {hist!r})"
            )
        want = history_length * sum(dims[t] for t in history_terms)
        got = next(t[1] for t in terms if t[0] == HISTORY_TERM)
        if got != want:
            raise PolicyFormatError(f"{path}: {HISTORY_TERM} has dim {got}, its history description gives {want}")
    clock = d.get("gait_clock") or {}
    try:
        gait_frequency = float(clock.get("frequency", 0.0)) if isinstance(clock, dict) else math.nan
    except (TypeError, ValueError):
        gait_frequency = math.nan
    if any(t[0] == "gait_phase" for t in terms) and not (math.isfinite(gait_frequency) and gait_frequency > 0):
        raise PolicyFormatError(
            f"{path}: the policy observes gait_phase but gait_clock.frequency is not a positive number"
        )
    onnx = d.get("onnx") or {}
    meta = PolicyMeta(
        directory=path.parent,
        task=str(d.get("task", "")),
        robot=robot,
        joint_names=names,
        default_joint_pos=_vec(d, "default_joint_pos", n),
        action_scale=_num(d, "action_scale"),
        clip_actions=_num(d, "clip_actions"),
        kp=_vec(d, "kp", n),
        kd=_vec(d, "kd", n),
        torque_limits=_vec(d, "torque_limits", n),
        joint_pos_limits=lims,
        control_dt=_num(d, "control_dt"),
        physics_dt=_num(d, "physics_dt"),
        obs_dim=obs_dim,
        obs_clip=_num(obs, "clip"),
        obs_terms=terms,
        propulsion_modes=modes,
        files=dict(d.get("files") or {"onnx": "policy.onnx", "torchscript": "policy.pt"}),
        onnx_input=str(onnx.get("input", "obs")),
        onnx_output=str(onnx.get("output", "actions")),
        gait_frequency=gait_frequency if math.isfinite(gait_frequency) else 0.0,
        history_length=history_length,
        history_terms=history_terms,
        joint_control=control,
        velocity_action_scale=_num(d, "velocity_action_scale") if go2.CONTROL_VELOCITY in control else 0.0,
    )
    if np.any(meta.kp < 0) or np.any(meta.kd < 0):
        raise PolicyFormatError(f"{path}: negative gains")
    return meta


WARM_UP_RUNS = 10
"""Policy runs PolicyRunner makes at construction, before any control step."""


class PolicyRunner:
    """obs (dim,) float32 -> actions (n,) float32 through ONNX Runtime or TorchScript."""

    def __init__(self, meta: PolicyMeta, backend: str = "onnx"):
        self.backend = backend
        if backend == "onnx":
            import onnxruntime as ort

            opts = ort.SessionOptions()
            opts.intra_op_num_threads = 1
            opts.inter_op_num_threads = 1
            opts.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
            opts.add_session_config_entry("session.intra_op.allow_spinning", "0")  # sleep, don't spin
            opts.add_session_config_entry("session.inter_op.allow_spinning", "0")
            f = meta.directory / meta.files.get("onnx", "policy.onnx")
            self._sess = ort.InferenceSession(str(f), opts, providers=["CPUExecutionProvider"])
            inputs = [i.name for i in self._sess.get_inputs()]
            if meta.onnx_input not in inputs:
                raise PolicyFormatError(f"{f}: no input {meta.onnx_input!r} (has {inputs})")
            self._in, self._out = meta.onnx_input, meta.onnx_output
        elif backend == "torchscript":
            import torch

            torch.set_num_threads(1)
            f = meta.directory / meta.files.get("torchscript", "policy.pt")
            self._module = torch.jit.load(str(f), map_location="cpu").eval()
            self._torch = torch
        else:
            raise ValueError(f"backend must be 'onnx' or 'torchscript', got {backend!r}")
        out = self(np.zeros(meta.obs_dim, dtype=np.float32))
        if out.shape != (meta.num_joints,):
            raise PolicyFormatError(f"policy output has shape {out.shape}, expected ({meta.num_joints},)")
        # A few more runs on varied input: the runtime's first runs allocate and plan, and
        # that belongs to the start-up, not to the first control steps.
        rng = np.random.default_rng(0)
        for _ in range(WARM_UP_RUNS):
            self(rng.normal(0.0, 1.0, meta.obs_dim).astype(np.float32))

    def __call__(self, obs: np.ndarray) -> np.ndarray:
        x = obs.reshape(1, -1).astype(np.float32, copy=False)
        if self.backend == "onnx":
            return np.asarray(self._sess.run([self._out], {self._in: x})[0], dtype=np.float32).reshape(-1)
        with self._torch.inference_mode():
            return self._module(self._torch.from_numpy(x)).numpy().astype(np.float32).reshape(-1)


def projected_gravity(quat_wxyz) -> np.ndarray:
    """World gravity direction (0, 0, -1) in the frame of the unit quaternion (w, x, y, z);
    (..., 4) quaternions give (..., 3)."""
    q = np.asarray(quat_wxyz, np.float64)
    one = q.ndim == 1  # the bridge, every control step: plain floats are 6x faster than array ops here
    w, x, y, z = (float(v) for v in q) if one else np.moveaxis(q, -1, 0)
    # third row of R^T, negated: R^T (0, 0, -1) = -(R[2, 0], R[2, 1], R[2, 2])
    g = (2.0 * (x * z - w * y), 2.0 * (y * z + w * x), 1.0 - 2.0 * (x * x + y * y))
    return -(np.array(g) if one else np.stack(g, axis=-1))


def gravity_tilt_deg(gravity):
    """Degrees between the frame's z axis and the vertical, from its projected gravity
    (..., 3) (0: upright, 180: upside down); a float for one frame."""
    g = np.asarray(gravity, np.float64)
    if g.ndim == 1:
        return math.degrees(math.acos(max(-1.0, min(1.0, -float(g[2])))))
    return np.degrees(np.arccos(np.clip(-g[..., 2], -1.0, 1.0)))


def tilt_deg(quat_wxyz):
    """Degrees between the frame's z axis and the vertical (0: upright, 180: upside down);
    a float for one quaternion, an array for (..., 4)."""
    return gravity_tilt_deg(projected_gravity(quat_wxyz))


def yaw_of(quat_wxyz) -> float:
    """Heading (rad, about world z, +-pi) of the unit quaternion (w, x, y, z): the numpy twin
    of `utils.math.yaw_from_quat`, for the robot side, which runs without torch."""
    w, x, y, z = (float(v) for v in quat_wxyz)
    return math.atan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))


class ObservationBuilder:
    """Actor observation from robot state, operator input and the previous action."""

    def __init__(self, meta: PolicyMeta):
        self.meta = meta
        self._buf = np.zeros(meta.obs_dim, dtype=np.float32)
        self._pos = meta.position_mask
        scales = {name: scale for name, _, scale in meta.obs_terms}
        self._hist_scales = [(t, scales.get(t, 1.0)) for t in meta.history_terms]
        dims = term_dims(meta.num_joints)
        width = sum(dims[t] for t in meta.history_terms)
        self._history = np.zeros((meta.history_length, width), dtype=np.float64)

    def raw_terms(self, state, commands, mode_mask, last_actions, step: int = 0) -> dict[str, np.ndarray]:
        """`step`: policy steps since the policy started (the gait clock: phase 2 pi f step dt,
        as in training, where it starts at 0 with every episode)."""
        phase = 2.0 * math.pi * self.meta.gait_frequency * step * self.meta.control_dt
        return {
            "gait_phase": np.array([math.sin(phase), math.cos(phase)]),
            "commands": np.asarray(commands, dtype=np.float64),
            "mode_mask": np.asarray(mode_mask, dtype=np.float64),
            "ang_vel": np.asarray(state.gyro, dtype=np.float64),
            "projected_gravity": projected_gravity(state.quat),
            # A wheel's angle says nothing (it turns freely): velocity joints read 0, as in training.
            "joint_pos": (np.asarray(state.q, dtype=np.float64) - self.meta.default_joint_pos) * self._pos,
            "joint_vel": np.asarray(state.dq, dtype=np.float64),
            "actions": np.asarray(last_actions, dtype=np.float64),
        }

    def build(self, state, commands, mode_mask, last_actions, step: int = 0) -> np.ndarray:
        """The observation of policy step `step` (0: the policy's first; it also clears
        the history, as an episode start does in training)."""
        raw = self.raw_terms(state, commands, mode_mask, last_actions, step)
        if step == 0:
            self._history[:] = 0.0
        raw[HISTORY_TERM] = self._history.reshape(-1)
        i = 0
        for name, dim, scale in self.meta.obs_terms:
            self._buf[i : i + dim] = raw[name] * scale
            i += dim
        if self.meta.history_length:
            now = np.concatenate([raw[t] * s for t, s in self._hist_scales])
            self._history[1:] = self._history[:-1]
            self._history[0] = now
        np.clip(self._buf, -self.meta.obs_clip, self.meta.obs_clip, out=self._buf)
        return self._buf
