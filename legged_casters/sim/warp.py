"""MuJoCo Warp backend: all envs are worlds of one batched `mujoco_warp` Data.

* Model fields in `RANDOMIZABLE_FIELDS` are given a leading world dimension
  (`put_model(..., batch_sizes={field: num_envs})`); MuJoCo Warp's kernels read
  world `w` of a batched field and world 0 of a shared one, so writing row `w`
  randomises env `w` only.
* The torch tensors exposed (`qpos`, `qvel`, `sensordata`, `ctrl`, model fields) are
  `wp.to_torch` views of the Warp arrays: no copies, and writes through them land in
  the simulation.
* On CUDA the `decimation` substeps (and the forward pass used by `reset`) are
  captured once into CUDA graphs and replayed; on the CPU device they run as a plain
  loop (slow: a single thread runs the kernels; meant for tests on machines without a GPU).

Warp computes in float32; the CPU backend in float64.
"""

from __future__ import annotations

import mujoco
import numpy as np
import torch
import warp as wp

from legged_casters.sim.base import RANDOMIZABLE_FIELDS, IndexLike, SimBackend, initial_data

try:
    import mujoco_warp as mjw
except ImportError as exc:  # pragma: no cover - mujoco_warp is a hard dependency of the package
    raise ImportError("the Warp backend needs the mujoco_warp package") from exc


def _warp_device(device: torch.device) -> str:
    if device.type == "cuda":
        return f"cuda:{device.index or 0}"
    if device.type == "cpu":
        return "cpu"
    raise ValueError(f"the Warp backend runs on a cpu or cuda torch device, got {device}")


@wp.kernel
def _delayed_ctrl(
    substep: int,
    held_steps: wp.array(dtype=wp.int32),
    held: wp.array2d(dtype=wp.float32),
    target: wp.array2d(dtype=wp.float32),
    ctrl: wp.array2d(dtype=wp.float32),
):
    """Action latency: world w applies `held` for its first held_steps[w] substeps, then `target`."""
    w, i = wp.tid()
    if substep < held_steps[w]:
        ctrl[w, i] = held[w, i]
    else:
        ctrl[w, i] = target[w, i]


@wp.kernel
def _record_state(
    slot: int,
    qpos: wp.array2d(dtype=wp.float32),
    qvel: wp.array2d(dtype=wp.float32),
    qpos_out: wp.array3d(dtype=wp.float32),
    qvel_out: wp.array3d(dtype=wp.float32),
):
    """Observation delay: world w's qpos and qvel into row `slot` of its record (0: the step's
    start, s: after substep s)."""
    w = wp.tid()
    for i in range(qpos.shape[1]):
        qpos_out[w, slot, i] = qpos[w, i]
    for i in range(qvel.shape[1]):
        qvel_out[w, slot, i] = qvel[w, i]


class WarpBackend(SimBackend):
    name = "warp"

    def __init__(
        self,
        model: mujoco.MjModel,
        num_envs: int,
        decimation: int,
        device: str | torch.device = "cpu",
        nconmax: int = 32,
        njmax: int | None = None,
        use_graph: bool | None = None,
    ):
        """`nconmax`: contacts per world (a standing robot has 4, a fallen one more);
        `njmax`: constraint rows per world, default 3 per contact (elliptic cone,
        condim 3) plus joint limits and frictionloss rows. `use_graph`: capture CUDA
        graphs (default: when on CUDA)."""
        super().__init__(model, num_envs, decimation, device)
        wp.init()
        self.wp_device = wp.get_device(_warp_device(self.device))
        self.use_graph = self.wp_device.is_cuda if use_graph is None else bool(use_graph)
        if self.use_graph and not self.wp_device.is_cuda:
            raise ValueError("CUDA graphs need a CUDA device")
        if njmax is None:
            njmax = 3 * nconmax + 2 * model.njnt + model.nv
        self.nconmax, self.njmax = int(nconmax), int(njmax)

        mjd = initial_data(model)
        with wp.ScopedDevice(self.wp_device):
            self.wm = mjw.put_model(model, batch_sizes={f: num_envs for f in RANDOMIZABLE_FIELDS})
            self.wd = mjw.put_data(model, mjd, nworld=num_envs, nconmax=self.nconmax, njmax=self.njmax)

        self._qpos = wp.to_torch(self.wd.qpos)
        self._qvel = wp.to_torch(self.wd.qvel)
        self._sens = wp.to_torch(self.wd.sensordata)
        self._ctrl = wp.to_torch(self.wd.ctrl)
        self._xfrc = wp.to_torch(self.wd.xfrc_applied)  # (num_envs, nbody, 6): force, torque
        self._warmstart = wp.to_torch(self.wd.qacc_warmstart)
        self._act = wp.to_torch(self.wd.act) if model.na else None
        self._fields = {name: wp.to_torch(getattr(self.wm, name)) for name in RANDOMIZABLE_FIELDS}
        # Gravity is an Option field that put_model does not batch; MuJoCo Warp's kernels read
        # opt.gravity[world % its length], so one row per world gives each env its own.
        with wp.ScopedDevice(self.wp_device):
            self.wm.opt.gravity = wp.array(np.tile(model.opt.gravity, (num_envs, 1)), dtype=wp.vec3)
        self._gravity = wp.to_torch(self.wm.opt.gravity)
        for name, view in self._fields.items():
            if view.shape[0] != num_envs:
                raise RuntimeError(f"mujoco_warp did not batch model field {name}: shape {tuple(view.shape)}")
        self._xfrc_pending = False
        self._step_graph = None
        self._delayed_graph = None
        self._forward_graph = None
        self._delay: dict[str, wp.array] | None = None  # action-latency buffers, made on first use
        self._record: tuple[wp.array, wp.array] | None = None  # substep states (keep_substep_states)

    # --- views -----------------------------------------------------------------------
    @property
    def qpos(self) -> torch.Tensor:
        return self._qpos

    @property
    def qvel(self) -> torch.Tensor:
        return self._qvel

    @property
    def sensordata(self) -> torch.Tensor:
        return self._sens

    @property
    def ctrl(self) -> torch.Tensor:
        return self._ctrl

    # --- simulation --------------------------------------------------------------------
    def _substeps(self) -> None:
        for k in range(self.decimation):
            self._record_substep(k)
            mjw.step(self.wm, self.wd)

    def _delayed_substeps(self) -> None:
        d = self._delay
        for k in range(self.decimation):
            self._record_substep(k)
            inputs = [k, d["steps"], d["held"], d["target"], self.wd.ctrl]
            wp.launch(_delayed_ctrl, dim=(self.num_envs, self.nu), inputs=inputs)
            mjw.step(self.wm, self.wd)

    def _record_substep(self, slot: int) -> None:
        """The state before substep `slot` (= after substep slot - 1), kept for delayed_state."""
        if self._record is not None:
            inputs = [slot, self.wd.qpos, self.wd.qvel, *self._record]
            wp.launch(_record_state, dim=self.num_envs, inputs=inputs)

    def keep_substep_states(self) -> None:
        if self._record is None:
            with wp.ScopedDevice(self.wp_device):
                self._record = (
                    wp.zeros((self.num_envs, self.decimation, self.nq), dtype=wp.float32),
                    wp.zeros((self.num_envs, self.decimation, self.nv), dtype=wp.float32),
                )
            self._step_graph = self._delayed_graph = None  # recapture with the recording
        self._keeping_substeps = True

    def delayed_state(self, steps: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        k = self._check_delay_steps(steps).to(self.device)
        if self._record is None:  # nothing kept yet: every lag is 0 (checked above)
            return self._qpos.clone(), self._qvel.clone()
        # A gather over every env and a select, no host read: slot 0 is the step's start, s
        # the state after substep s; an env with lag 0 (or reset since) takes its present.
        rows = torch.arange(self.num_envs, device=self.device)
        slot = (self.decimation - k).clamp(max=self.decimation - 1)
        lagged = (k > 0).unsqueeze(1)
        qpos = torch.where(lagged, wp.to_torch(self._record[0])[rows, slot], self._qpos)
        return qpos, torch.where(lagged, wp.to_torch(self._record[1])[rows, slot], self._qvel)

    def _forward(self) -> None:
        mjw.forward(self.wm, self.wd)

    def _run(self, fn, graph_attr: str) -> None:
        with wp.ScopedDevice(self.wp_device):
            if not self.wp_device.is_cuda:
                fn()
                return
            # torch writes the inputs on its current stream, Warp runs on its own:
            # order the two both ways around the launch.
            torch_stream = wp.stream_from_torch(torch.cuda.current_stream(self.device))
            warp_stream = wp.get_stream(self.wp_device)
            warp_stream.wait_stream(torch_stream)
            if not self.use_graph:
                fn()
            else:
                graph = getattr(self, graph_attr)
                if graph is None:
                    graph = self._capture(fn)
                    setattr(self, graph_attr, graph)
                wp.capture_launch(graph, stream=warp_stream)
            torch_stream.wait_stream(warp_stream)

    def _capture(self, fn):
        """Capture `fn` into a CUDA graph. Warp compiles and loads modules on first
        launch, which cannot happen inside a capture: run once for real (restoring the
        state afterwards), then capture."""
        live = [self._qpos, self._qvel, self._warmstart, self._sens, wp.to_torch(self.wd.time)]
        if self._act is not None:
            live.append(self._act)
        torch.cuda.synchronize(self.device)
        saved = [t.clone() for t in live]
        torch.cuda.synchronize(self.device)
        fn()
        wp.synchronize_device(self.wp_device)
        for t, s in zip(live, saved, strict=True):
            t.copy_(s)
        torch.cuda.synchronize(self.device)
        with wp.ScopedCapture(device=self.wp_device) as capture:
            fn()
        return capture.graph

    def step(
        self, ctrl: torch.Tensor, held: torch.Tensor | None = None, held_steps: torch.Tensor | None = None
    ) -> None:
        self._check_rows("ctrl", ctrl, self.num_envs, (self.nu,))
        if held_steps is None:
            self._ctrl.copy_(ctrl)
            self._run(self._substeps, "_step_graph")
        else:
            self._check_rows("held", held, self.num_envs, (self.nu,))
            if self._delay is None:
                with wp.ScopedDevice(self.wp_device):
                    self._delay = {
                        "steps": wp.zeros(self.num_envs, dtype=wp.int32),
                        "held": wp.zeros((self.num_envs, self.nu), dtype=wp.float32),
                        "target": wp.zeros((self.num_envs, self.nu), dtype=wp.float32),
                    }
            d = self._delay
            wp.to_torch(d["steps"]).copy_(held_steps.reshape(-1))
            wp.to_torch(d["held"]).copy_(held)
            wp.to_torch(d["target"]).copy_(ctrl)
            self._run(self._delayed_substeps, "_delayed_graph")
        if self._xfrc_pending:
            self._xfrc.zero_()
            self._xfrc_pending = False

    def reset(self, env_ids: IndexLike, qpos: torch.Tensor, qvel: torch.Tensor) -> None:
        ids_np = self.env_index(env_ids)
        self._check_rows("qpos", qpos, len(ids_np), (self.nq,))
        self._check_rows("qvel", qvel, len(ids_np), (self.nv,))
        if len(ids_np) == 0:
            return
        ids = torch.as_tensor(ids_np, device=self.device)
        keep = torch.ones(self.num_envs, dtype=torch.bool, device=self.device)
        keep[ids] = False
        kept_sens = self._sens[keep].clone()
        self._qpos[ids] = qpos.to(self.device, self._qpos.dtype)
        self._qvel[ids] = qvel.to(self.device, self._qvel.dtype)
        self._warmstart[ids] = 0.0
        self._xfrc[ids] = 0.0
        if self._act is not None:
            self._act[ids] = 0.0
        # Forward runs on every world; it leaves qpos/qvel/warmstart alone, but would
        # re-evaluate the other worlds' sensors at their current state: keep theirs.
        self._run(self._forward, "_forward_graph")
        self._sens[keep] = kept_sens

    def set_model_field(self, name: str, env_ids: IndexLike, values: torch.Tensor | np.ndarray) -> None:
        shape = self.field_shape(name)
        ids_np = self.env_index(env_ids)
        view = self._fields[name]
        vals = torch.as_tensor(values).to(self.device, view.dtype)
        self._check_rows(name, vals, len(ids_np), shape)
        view[torch.as_tensor(ids_np, device=self.device)] = vals

    def get_model_field(self, name: str) -> torch.Tensor:
        self.field_shape(name)
        return self._fields[name].clone()

    def set_gravity(self, env_ids: IndexLike, gravity: torch.Tensor | np.ndarray) -> None:
        ids_np = self.env_index(env_ids)
        g = torch.as_tensor(gravity).to(self.device, self._gravity.dtype)
        self._check_rows("gravity", g, len(ids_np), (3,))
        self._gravity[torch.as_tensor(ids_np, device=self.device)] = g

    def apply_force(self, env_ids: IndexLike, body: str | int, force: torch.Tensor) -> None:
        ids_np = self.env_index(env_ids)
        bid = self.body_id(body)
        f = torch.as_tensor(force).to(self.device, self._xfrc.dtype)
        if f.ndim != 2 or f.shape[0] != len(ids_np) or f.shape[1] not in (3, 6):
            raise ValueError(f"force must have shape ({len(ids_np)}, 3) or ({len(ids_np)}, 6), got {tuple(f.shape)}")
        ids = torch.as_tensor(ids_np, device=self.device)
        self._xfrc[ids, bid, : f.shape[1]] = f
        self._xfrc_pending = True

    def contact_overflow(self) -> bool:
        """True when a step needed more contacts or constraint rows than allocated."""
        nacon = int(wp.to_torch(self.wd.nacon).max())
        nefc = int(wp.to_torch(self.wd.nefc).max())
        return nacon >= self.nconmax * self.num_envs or nefc >= self.njmax
