"""MuJoCo C backend: all envs stepped by `mujoco.rollout` on a persistent thread pool.

Each env has its own MjModel (a copy of the nominal one, so model fields can be
randomised per env); the pool has one MjData per thread. A control step is one
rollout call of `decimation` physics steps per env with constant control.

State lives in persistent numpy buffers; the torch tensors the backend exposes are
`torch.from_numpy` views of them (no copies on a CPU torch device):

* `_state` (num_envs, nstate): mjSTATE_FULLPHYSICS vectors, the rollout's initial
  state; `qpos` / `qvel` are column views of it;
* `_state_out` (num_envs, decimation, nstate) and `_sens_out` (num_envs, decimation,
  nsensordata): the rollout's outputs; the last substep's state is copied into
  `_state` after each step, `sensordata` is a view of the last substep's row;
* `_control` (num_envs, decimation, ncontrol): the constant control repeated per substep.

The rollout cannot hand the constraint solver's last acceleration (mj_step's
qacc_warmstart) back, so each call is warmstarted with the last substep's velocity
change / dt instead. Against a plain mj_step loop this keeps the state within ~1e-5
over 10 control steps (a zero warmstart: up to 6e-3, the solver stops at its
tolerance from a different start).
"""

from __future__ import annotations

import copy
import warnings

import mujoco
import mujoco.rollout
import numpy as np
import torch

from legged_casters.sim.base import RANDOMIZABLE_FIELDS, IndexLike, SimBackend, initial_data, usable_cpus

_FULL = mujoco.mjtState.mjSTATE_FULLPHYSICS.value
_CTRL = mujoco.mjtState.mjSTATE_CTRL.value
_CTRL_XFRC = mujoco.mjtState.mjSTATE_CTRL.value | mujoco.mjtState.mjSTATE_XFRC_APPLIED.value


def _to_numpy(x: torch.Tensor | np.ndarray) -> np.ndarray:
    if isinstance(x, torch.Tensor):
        return x.detach().to("cpu", torch.float64).numpy()
    return np.asarray(x, dtype=np.float64)


class CpuBackend(SimBackend):
    name = "cpu"

    def __init__(
        self,
        model: mujoco.MjModel,
        num_envs: int,
        decimation: int,
        device: str | torch.device = "cpu",
        nthread: int | None = None,
    ):
        super().__init__(model, num_envs, decimation, device)
        if model.ntexdata * num_envs > 2**30:
            warnings.warn(
                f"{num_envs} model copies with {model.ntexdata / 2**20:.1f} MB of texture each; "
                "build the model with legged_casters.sim.base.physics_model() to drop the textures",
                stacklevel=2,
            )
        self.nthread = int(nthread or usable_cpus())
        self._pool = mujoco.rollout.Rollout(nthread=self.nthread)
        self._models = [copy.copy(model) for _ in range(num_envs)]
        self._datas = [mujoco.MjData(model) for _ in range(self.nthread)]
        self._scratch = mujoco.MjData(model)

        self.nstate = mujoco.mj_stateSize(model, _FULL)
        # mjSTATE_FULLPHYSICS starts with time (1), qpos (nq), qvel (nv).
        self._qpos_sl = slice(1, 1 + self.nq)
        self._qvel_sl = slice(1 + self.nq, 1 + self.nq + self.nv)

        self._state = np.empty((num_envs, self.nstate))
        init = initial_data(model)
        mujoco.mj_getState(model, init, self._state[0], _FULL)
        if not (
            np.array_equal(self._state[0, self._qpos_sl], init.qpos)
            and np.array_equal(self._state[0, self._qvel_sl], init.qvel)
        ):
            raise RuntimeError("unexpected mjSTATE_FULLPHYSICS layout in this MuJoCo version")
        self._state[:] = self._state[0]
        self._state_start: np.ndarray | None = None  # the state as each step began (keep_substep_states)
        self._state_out = np.empty((num_envs, decimation, self.nstate))
        self._sens_out = np.empty((num_envs, decimation, self.nsensordata))
        self._sens_out[:, -1] = init.sensordata
        self._ctrl = np.tile(init.ctrl, (num_envs, 1))
        self._warmstart = np.tile(init.qacc_warmstart, (num_envs, 1))
        self._control = np.zeros((num_envs, decimation, self.nu))
        nxfrc = mujoco.mj_stateSize(model, _CTRL_XFRC)
        self._control_xfrc = np.zeros((num_envs, decimation, nxfrc))
        self._xfrc = np.zeros((num_envs, self.nbody, 6))
        self._xfrc_pending = False

        self._np_qpos = self._state[:, self._qpos_sl]
        self._np_qvel = self._state[:, self._qvel_sl]
        self._np_sens = self._sens_out[:, -1, :]
        self._on_cpu = self.device.type == "cpu"
        self._views = {
            "qpos": torch.from_numpy(self._np_qpos),
            "qvel": torch.from_numpy(self._np_qvel),
            "sensordata": torch.from_numpy(self._np_sens),
            "ctrl": torch.from_numpy(self._ctrl),
        }
        self._device_copies: dict[str, torch.Tensor] = {}
        self._refresh_device_copies()

    # --- views -----------------------------------------------------------------------
    def _refresh_device_copies(self) -> None:
        """On a non-CPU torch device keep device tensors that are refreshed in place."""
        if self._on_cpu:
            return
        for key, view in self._views.items():
            if key not in self._device_copies:
                self._device_copies[key] = view.to(self.device)
            else:
                self._device_copies[key].copy_(view, non_blocking=False)

    def _view(self, key: str) -> torch.Tensor:
        return self._views[key] if self._on_cpu else self._device_copies[key]

    @property
    def qpos(self) -> torch.Tensor:
        return self._view("qpos")

    @property
    def qvel(self) -> torch.Tensor:
        return self._view("qvel")

    @property
    def sensordata(self) -> torch.Tensor:
        return self._view("sensordata")

    @property
    def ctrl(self) -> torch.Tensor:
        return self._view("ctrl")

    def substep_sensordata(self) -> torch.Tensor:
        out = torch.from_numpy(self._sens_out)
        return out if self._on_cpu else out.to(self.device)

    # --- simulation --------------------------------------------------------------------
    def step(
        self, ctrl: torch.Tensor, held: torch.Tensor | None = None, held_steps: torch.Tensor | None = None
    ) -> None:
        self._check_rows("ctrl", ctrl, self.num_envs, (self.nu,))
        self._ctrl[:] = _to_numpy(ctrl)
        if self._xfrc_pending:
            control, spec = self._control_xfrc, _CTRL_XFRC
            control[:, :, : self.nu] = self._ctrl[:, None, :]
            control[:, :, self.nu :] = self._xfrc.reshape(self.num_envs, 1, -1)
        else:
            control, spec = self._control, _CTRL
            control[:] = self._ctrl[:, None, :]
        if held_steps is not None:
            self._check_rows("held", held, self.num_envs, (self.nu,))
            k = _to_numpy(held_steps).reshape(-1, 1)
            first = np.arange(self.decimation)[None, :] < k  # (num_envs, decimation)
            envs, substeps = np.nonzero(first)
            control[envs, substeps, : self.nu] = _to_numpy(held)[envs]
        if self._state_start is not None:
            self._state_start[:] = self._state
        self._pool.rollout(
            self._models,
            self._datas,
            self._state,
            control,
            control_spec=spec,
            skip_checks=True,
            nstep=self.decimation,
            initial_warmstart=self._warmstart,
            state=self._state_out,
            sensordata=self._sens_out,
        )
        # Warmstart of the next call: the rollout cannot return the solver's last qacc;
        # the last substep's velocity change / dt is close to it (exact for Euler).
        prev = self._state_out[:, -2] if self.decimation > 1 else self._state
        np.subtract(self._state_out[:, -1, self._qvel_sl], prev[:, self._qvel_sl], out=self._warmstart)
        self._warmstart /= self.physics_dt
        self._state[:] = self._state_out[:, -1]
        if self._xfrc_pending:
            self._xfrc[:] = 0.0
            self._xfrc_pending = False
        self._refresh_device_copies()

    def keep_substep_states(self) -> None:
        # The rollout writes every substep's state anyway (_state_out); only the start is kept.
        if self._state_start is None:
            self._state_start = self._state.copy()
        self._keeping_substeps = True

    def delayed_state(self, steps: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        k = self._check_delay_steps(steps).cpu().numpy()
        out = self._state.copy()
        for lag in np.unique(k[k > 0]):
            rows = np.nonzero(k == lag)[0]
            slot = self.decimation - lag  # 0: the step's start, s: after substep s
            out[rows] = self._state_start[rows] if slot == 0 else self._state_out[rows, slot - 1]
        qpos = torch.from_numpy(out[:, self._qpos_sl]).to(self.device)
        return qpos, torch.from_numpy(out[:, self._qvel_sl]).to(self.device)

    def reset(self, env_ids: IndexLike, qpos: torch.Tensor, qvel: torch.Tensor) -> None:
        ids = self.env_index(env_ids)
        self._check_rows("qpos", qpos, len(ids), (self.nq,))
        self._check_rows("qvel", qvel, len(ids), (self.nv,))
        qpos_np, qvel_np = _to_numpy(qpos), _to_numpy(qvel)
        d = self._scratch
        for row, env in enumerate(ids):
            m = self._models[env]
            mujoco.mj_resetData(m, d)
            d.qpos[:] = qpos_np[row]
            d.qvel[:] = qvel_np[row]
            d.time = self._state[env, 0]
            d.ctrl[:] = self._ctrl[env]
            mujoco.mj_forward(m, d)
            mujoco.mj_getState(m, d, self._state[env], _FULL)
            self._warmstart[env] = d.qacc
            self._np_sens[env] = d.sensordata
        self._xfrc[ids] = 0.0
        self._refresh_device_copies()

    def set_model_field(self, name: str, env_ids: IndexLike, values: torch.Tensor | np.ndarray) -> None:
        shape = self.field_shape(name)
        ids = self.env_index(env_ids)
        vals = _to_numpy(values)
        self._check_rows(name, vals, len(ids), shape)
        for row, env in enumerate(ids):
            getattr(self._models[env], name)[...] = vals[row]

    def get_model_field(self, name: str) -> torch.Tensor:
        if name not in RANDOMIZABLE_FIELDS:
            self.field_shape(name)  # raises with the list of allowed fields
        out = np.stack([getattr(m, name) for m in self._models])
        return torch.from_numpy(out).to(self.device)

    def set_gravity(self, env_ids: IndexLike, gravity: torch.Tensor | np.ndarray) -> None:
        ids = self.env_index(env_ids)
        g = _to_numpy(gravity)
        self._check_rows("gravity", g, len(ids), (3,))
        for row, env in enumerate(ids):
            self._models[env].opt.gravity[:] = g[row]

    def apply_force(self, env_ids: IndexLike, body: str | int, force: torch.Tensor) -> None:
        ids = self.env_index(env_ids)
        bid = self.body_id(body)
        f = _to_numpy(force)
        if f.ndim != 2 or f.shape[0] != len(ids) or f.shape[1] not in (3, 6):
            raise ValueError(f"force must have shape ({len(ids)}, 3) or ({len(ids)}, 6), got {f.shape}")
        self._xfrc[ids, bid, : f.shape[1]] = f
        self._xfrc_pending = True

    def close(self) -> None:
        if self._pool is not None:
            self._pool.close()
            self._pool = None
