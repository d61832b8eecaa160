"""The simulation backend interface shared by the MuJoCo C and MuJoCo Warp backends.

A backend simulates `num_envs` copies of one robot model. The env layer talks to it
only through torch tensors shaped (num_envs, n):

* `qpos`, `qvel`, `sensordata`, `ctrl`: live views of the backend's state buffers
  (no copies; they change in place on every `step` / `reset`, clone what you keep);
* `step(ctrl)`: set the position-actuator targets and advance `decimation` physics
  steps with that constant control;
* `reset(env_ids, qpos, qvel)`: overwrite the state of selected envs and recompute
  their derived quantities, so their `sensordata` matches the new state;
* `set_model_field` / `get_model_field`: per-env domain randomisation of the model
  parameters in `RANDOMIZABLE_FIELDS`;
* `keep_substep_states()` / `delayed_state(steps)`: the state each env had a given number
  of substeps before the end of the last step (an observation delay shorter than a step);
* `set_gravity(env_ids, gravity)`: per-env gravity vector (a tilted ground);
* `apply_force(env_ids, body, force)`: a Cartesian force (and optionally torque) on a
  body, held for the next `step` only (one control period), then cleared.

Timing convention of `sensordata` after `step`: as MuJoCo's `mj_step` leaves it, i.e.
evaluated by the forward pass of the last physics substep, at the state *before* that
substep's integration (one physics step, 2 ms, behind `qpos`/`qvel`). Both backends
follow this convention; after `reset` the sensors of the reset envs match their new state.

Changes of `body_mass` / `body_ipos` act on the dynamics directly; quantities MuJoCo
derives from them at compile time (`body_subtreemass`, the `*_invweight0` used for
constraint regularisation) are not recomputed, on either backend.
"""

from __future__ import annotations

import abc
import os
from collections.abc import Sequence
from pathlib import Path

import mujoco
import numpy as np
import torch

RANDOMIZABLE_FIELDS: tuple[str, ...] = (
    "geom_friction",
    "body_mass",
    "body_ipos",
    "dof_damping",
    "dof_frictionloss",
    "actuator_gainprm",
    "actuator_biasprm",
    "actuator_forcerange",
)
"""MjModel fields that can be set per env."""

BACKEND_KINDS: tuple[str, ...] = ("auto", "cpu", "warp")

IndexLike = torch.Tensor | Sequence[int] | np.ndarray | slice | None


def usable_cpus() -> int:
    """CPU cores this process may run on: its affinity mask (taskset, a pinned rank of
    `train.py --procs`), not every core of the machine as os.cpu_count() says."""
    if hasattr(os, "sched_getaffinity"):
        return max(1, len(os.sched_getaffinity(0)))
    return os.cpu_count() or 1


def physics_model(source: mujoco.MjModel | mujoco.MjSpec | str | Path) -> mujoco.MjModel:
    """The nominal model for a backend, compiled without textures.

    The CPU backend holds one MjModel per env; the robot's floor and skybox textures
    alone are 5.5 MB per copy (22 GB at 4096 envs), the physics is 0.25 MB. Given an
    MjSpec or an MJCF path, the textures are dropped before compiling (element ids,
    and so all indices into the model, are unchanged); an MjModel is returned as is.
    """
    if isinstance(source, mujoco.MjModel):
        return source
    spec = source.copy() if isinstance(source, mujoco.MjSpec) else mujoco.MjSpec.from_file(str(source))
    for mat in spec.materials:
        mat.textures = [""] * len(mat.textures)
    for tex in list(spec.textures):
        spec.delete(tex)
    return spec.compile()


def initial_data(model: mujoco.MjModel) -> mujoco.MjData:
    """The state every env starts from: keyframe 0 when the model has one (the robot's
    "stand"), else qpos0; forward has been run."""
    data = mujoco.MjData(model)
    if model.nkey > 0:
        mujoco.mj_resetDataKeyframe(model, data, 0)
    mujoco.mj_forward(model, data)
    return data


def sensor_slices(model: mujoco.MjModel) -> dict[str, slice]:
    """Map every named sensor to its slice of `sensordata`."""
    out = {}
    for i in range(model.nsensor):
        name = mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_SENSOR, i)
        if not name:
            continue
        adr, dim = int(model.sensor_adr[i]), int(model.sensor_dim[i])
        out[name] = slice(adr, adr + dim)
    return out


class SimBackend(abc.ABC):
    """`num_envs` parallel copies of `model`, stepped `decimation` physics steps per control step."""

    name: str = "abstract"

    def __init__(self, model: mujoco.MjModel, num_envs: int, decimation: int, device: str | torch.device = "cpu"):
        if num_envs < 1:
            raise ValueError(f"num_envs must be >= 1, got {num_envs}")
        if decimation < 1:
            raise ValueError(f"decimation must be >= 1, got {decimation}")
        self.model = model
        self.num_envs = int(num_envs)
        self.decimation = int(decimation)
        self.device = torch.device(device)
        self.nq, self.nv, self.nu = model.nq, model.nv, model.nu
        self.nbody = model.nbody
        self.nsensordata = model.nsensordata
        self.physics_dt = float(model.opt.timestep)
        self.control_dt = self.physics_dt * self.decimation
        self._sensor_slices = sensor_slices(model)
        self._keeping_substeps = False

    # --- state views ---------------------------------------------------------------
    @property
    @abc.abstractmethod
    def qpos(self) -> torch.Tensor:
        """(num_envs, nq) generalized positions (live view)."""

    @property
    @abc.abstractmethod
    def qvel(self) -> torch.Tensor:
        """(num_envs, nv) generalized velocities (live view)."""

    @property
    @abc.abstractmethod
    def sensordata(self) -> torch.Tensor:
        """(num_envs, nsensordata) sensor values (live view)."""

    def substep_sensordata(self) -> torch.Tensor:
        """(num_envs, k, nsensordata): the sensor values after each physics substep of the
        last `step` where the backend keeps them (MuJoCo C: k = decimation), else after
        the last substep only (k = 1). Rows of a substep before a reset are stale."""
        return self.sensordata.unsqueeze(1)

    @abc.abstractmethod
    def keep_substep_states(self) -> None:
        """From the next `step` on, keep qpos and qvel at the start of each step and after
        each of its substeps, for `delayed_state` (observation delay). Off by default: a
        run without it records nothing."""

    @abc.abstractmethod
    def delayed_state(self, steps: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(qpos, qvel), (num_envs, nq) and (num_envs, nv): env i's state `steps[i]` physics
        substeps before now, 0 <= steps[i] <= decimation (0: the current state, as `qpos` /
        `qvel`; decimation: as the last `step` began). Needs `keep_substep_states()` before
        that step; an env reset since has only its current state (give it 0)."""

    def _check_delay_steps(self, steps: torch.Tensor) -> torch.Tensor:
        steps = torch.as_tensor(steps).reshape(-1).long()
        if steps.numel() != self.num_envs:
            raise ValueError(f"steps must have {self.num_envs} entries, got {steps.numel()}")
        lo, hi = (int(v) for v in torch.aminmax(steps))  # one read of the device for both
        if lo < 0 or hi > self.decimation:
            raise ValueError(f"steps must lie in [0, {self.decimation}] (the substeps of one step)")
        if hi > 0 and not self._keeping_substeps:
            raise RuntimeError("delayed_state needs keep_substep_states() before the step it looks into")
        return steps

    @property
    @abc.abstractmethod
    def ctrl(self) -> torch.Tensor:
        """(num_envs, nu) the actuator targets applied by the last `step` (live view)."""

    # --- simulation ----------------------------------------------------------------
    @abc.abstractmethod
    def step(
        self, ctrl: torch.Tensor, held: torch.Tensor | None = None, held_steps: torch.Tensor | None = None
    ) -> None:
        """Apply the PD targets `ctrl` (num_envs, nu) and advance `decimation` physics steps.
        With `held` (num_envs, nu) and `held_steps` (num_envs,) integers: env i applies
        `held[i]` for its first `held_steps[i]` substeps, then `ctrl[i]` (action latency)."""

    @abc.abstractmethod
    def reset(self, env_ids: IndexLike, qpos: torch.Tensor, qvel: torch.Tensor) -> None:
        """Set qpos (n, nq) / qvel (n, nv) of envs `env_ids` (None = all) and run forward for them."""

    @abc.abstractmethod
    def set_model_field(self, name: str, env_ids: IndexLike, values: torch.Tensor | np.ndarray) -> None:
        """Set MjModel field `name` of envs `env_ids` to `values`, shaped (n, *field_shape)."""

    @abc.abstractmethod
    def get_model_field(self, name: str) -> torch.Tensor:
        """Per-env values of field `name`, shaped (num_envs, *field_shape) (a copy)."""

    @abc.abstractmethod
    def set_gravity(self, env_ids: IndexLike, gravity: torch.Tensor | np.ndarray) -> None:
        """Set the gravity vector (n, 3), m/s^2 in the world frame, of envs `env_ids`: a
        tilted vector is a tilted ground plane (the env's slopes)."""

    @abc.abstractmethod
    def apply_force(self, env_ids: IndexLike, body: str | int, force: torch.Tensor) -> None:
        """Apply force (n, 3) or force+torque (n, 6), world frame at the body's CoM, during the next `step`."""

    # --- helpers -------------------------------------------------------------------
    def sensor_slice(self, name: str) -> slice:
        """Columns of `sensordata` that hold the named sensor."""
        try:
            return self._sensor_slices[name]
        except KeyError:
            raise KeyError(f"no sensor named {name!r}; model has {sorted(self._sensor_slices)}") from None

    def sensor(self, name: str) -> torch.Tensor:
        """(num_envs, dim) slice of `sensordata` of the named sensor (a view)."""
        return self.sensordata[:, self.sensor_slice(name)]

    @property
    def sensor_names(self) -> tuple[str, ...]:
        return tuple(self._sensor_slices)

    def body_id(self, body: str | int) -> int:
        if isinstance(body, str):
            bid = mujoco.mj_name2id(self.model, mujoco.mjtObj.mjOBJ_BODY, body)
            if bid < 0:
                raise KeyError(f"no body named {body!r}")
            return bid
        if not 0 <= int(body) < self.nbody:
            raise IndexError(f"body id {body} out of range [0, {self.nbody})")
        return int(body)

    def field_shape(self, name: str) -> tuple[int, ...]:
        """Shape of one env's value of a randomisable field (e.g. (ngeom, 3) for geom_friction)."""
        if name not in RANDOMIZABLE_FIELDS:
            raise KeyError(f"field {name!r} cannot be randomised; allowed: {RANDOMIZABLE_FIELDS}")
        return tuple(getattr(self.model, name).shape)

    def env_index(self, env_ids: IndexLike) -> np.ndarray:
        """Normalise env ids (None = all, slice, sequence, tensor, bool mask) to an int64 numpy array."""
        if env_ids is None:
            return np.arange(self.num_envs)
        if isinstance(env_ids, slice):
            return np.arange(self.num_envs)[env_ids]
        if isinstance(env_ids, torch.Tensor):
            env_ids = env_ids.detach().cpu().numpy()
        ids = np.asarray(env_ids)
        if ids.dtype == bool:
            if ids.shape != (self.num_envs,):
                raise ValueError(f"boolean env mask must have shape ({self.num_envs},), got {ids.shape}")
            return np.nonzero(ids)[0]
        ids = ids.astype(np.int64).reshape(-1)
        if ids.size and (ids.min() < 0 or ids.max() >= self.num_envs):
            raise IndexError(f"env ids out of range [0, {self.num_envs}): {ids}")
        return ids

    def _check_rows(self, what: str, values: torch.Tensor, n: int, shape: tuple[int, ...]) -> None:
        if tuple(values.shape) != (n, *shape):
            raise ValueError(f"{what} must have shape {(n, *shape)}, got {tuple(values.shape)}")

    def close(self) -> None:  # noqa: B027 - optional hook
        """Release threads / device memory held by the backend."""


def make_backend(
    kind: str, model: mujoco.MjModel, num_envs: int, decimation: int, device: str | torch.device | None = None
) -> SimBackend:
    """Create a backend: 'cpu' (MuJoCo C rollout), 'warp' (MuJoCo Warp) or 'auto'
    (Warp when CUDA is available, else CPU). `device` defaults to cuda:0 for Warp on
    a CUDA machine and to cpu otherwise."""
    if kind not in BACKEND_KINDS:
        raise ValueError(f"unknown sim backend {kind!r}; allowed: {', '.join(BACKEND_KINDS)}")
    if kind == "auto":
        kind = "warp" if torch.cuda.is_available() else "cpu"
    if kind == "cpu":
        from legged_casters.sim.cpu import CpuBackend

        return CpuBackend(model, num_envs, decimation, device or "cpu")
    from legged_casters.sim.warp import WarpBackend

    if device is None:
        device = "cuda:0" if torch.cuda.is_available() else "cpu"
    return WarpBackend(model, num_envs, decimation, device)
