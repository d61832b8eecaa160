"""The base legged env: what every task shares, on top of a simulation backend.

A task subclasses `LeggedEnv` and adds only what is its own: its observation terms
(`_obs_<name>` methods listed in `OBSERVATIONS`), its reward terms (`_reward_<name>`
methods, weighted by `cfg.rewards.scales`), and any extra state. The env talks to
the simulator only through `legged_casters.sim` (qpos, qvel, named sensors), so the
MuJoCo C and MuJoCo Warp backends serve every task unchanged. It implements the
rsl_rl 5.5 VecEnv contract: observations as a TensorDict of groups ("policy" for
the actor, "critic" for the privileged extras), extras["time_outs"] and per-term
episode sums in extras["log"].
"""

from __future__ import annotations

import contextlib
import fnmatch
import math

import mujoco
import numpy as np
import torch
from rsl_rl.env import VecEnv
from tensordict import TensorDict

from legged_casters.envs.config import LeggedEnvCfg
from legged_casters.robot import build, go2, terrain
from legged_casters.sim.base import make_backend, physics_model
from legged_casters.utils.math import quat_from_yaw, quat_rotate_inverse

CPU_DEFAULT_NUM_ENVS = 512
GPU_DEFAULT_NUM_ENVS = 4096


def resolve_backend(kind: str) -> str:
    if kind == "auto":
        return "warp" if torch.cuda.is_available() else "cpu"
    return kind


def _uniform(lo: float, hi: float, shape, device) -> torch.Tensor:
    return torch.rand(shape, device=device) * (hi - lo) + lo


def set_timestep(model: mujoco.MjModel, timestep: float) -> None:
    """Change a model's physics step in place, raising every geom's solref time constant
    to at least 2 x timestep (what MuJoCo would do silently, made explicit)."""
    model.opt.timestep = timestep
    model.geom_solref[:, 0] = np.maximum(model.geom_solref[:, 0], 2.0 * timestep)


class LeggedEnv(VecEnv):
    OBSERVATIONS: dict[str, tuple[str, ...]] = {"policy": (), "critic": ()}
    """Observation group -> term names, in order. The one place the layout is written."""
    COLLISION_SENSORS: tuple[str, ...] = ()
    """Contact sensors whose contact counts as a collision (reward term `collision`)."""

    def __init__(self, cfg: LeggedEnvCfg):
        self.cfg = cfg
        torch.manual_seed(cfg.seed)
        np.random.seed(cfg.seed)
        self.backend_kind = resolve_backend(cfg.sim.backend)
        if cfg.sim.device == "auto":
            device = "cuda:0" if self.backend_kind == "warp" and torch.cuda.is_available() else "cpu"
        else:
            device = cfg.sim.device
        self.device = torch.device(device)
        num_envs = cfg.num_envs or (GPU_DEFAULT_NUM_ENVS if self.backend_kind == "warp" else CPU_DEFAULT_NUM_ENVS)
        spec = mujoco.MjSpec.from_file(str(build.MODEL_FILES[cfg.robot]))
        self.course = None
        """The terrain course under the robots (terrain.Course), None on flat ground."""
        if cfg.terrain.segments:
            terrain.add_course(spec, cfg.terrain.segments, cfg.terrain.start_x, cfg.terrain.width)
            self.course = terrain.Course(cfg.terrain.segments, cfg.terrain.start_x)
        self.spawn_x: torch.Tensor | None = None
        """Where each robot starts along x at its reset (num_envs,), NaN: the origin (or the
        course draw); None: every robot as configured. Set by the evaluation to start a
        scenario on its hill; the trunk is lifted onto the ground there."""
        self.model = physics_model(spec)
        if cfg.sim.timestep is not None:
            set_timestep(self.model, cfg.sim.timestep)
        self.sim = make_backend(self.backend_kind, self.model, num_envs, cfg.sim.decimation, self.device)
        self.num_envs = num_envs
        self.layout = go2.action_layout(cfg.robot)
        """What each action drives (joints, position/velocity control, gains, limits)."""
        self.num_actions = len(self.layout)
        self.dt = self.sim.control_dt
        self.max_episode_length = int(math.ceil(cfg.episode_length_s / self.dt))
        self._init_indices()
        self._init_buffers()
        self._init_rewards()
        self._init_task_buffers()
        self.reset_idx(torch.arange(self.num_envs, device=self.device))
        self._init_observation_layout()

    # --- set-up ----------------------------------------------------------------------
    def _init_indices(self) -> None:
        m, dev = self.model, self.device
        layout = self.layout
        joints = [m.joint(j) for j in layout.joints]
        self.joint_qadr = torch.tensor([j.qposadr[0] for j in joints], device=dev)
        self.joint_dadr = torch.tensor([j.dofadr[0] for j in joints], device=dev)
        key = m.key(build.STAND_KEY).id
        self.nominal_qpos = torch.tensor(m.key_qpos[key], dtype=torch.float32, device=dev)
        self.default_joint_pos = torch.tensor(layout.default, device=dev)
        self.position_joints = torch.tensor(layout.position_mask, device=dev)
        """(num_actions,) bool: position-controlled (legs) vs velocity-controlled (wheels)."""
        ctl = self.cfg.control
        self.action_scales = torch.where(
            self.position_joints, torch.tensor(ctl.action_scale), torch.tensor(ctl.velocity_action_scale)
        ).to(dev)
        ranges = torch.tensor(layout.ranges, device=dev)
        mid, half = ranges.mean(1), (ranges[:, 1] - ranges[:, 0]) / 2
        soft = self.cfg.rewards.soft_joint_pos_limit
        # Velocity joints turn freely: their position limits are +-inf.
        inf = torch.full_like(mid, float("inf"))
        self.soft_joint_limits = torch.stack(
            [
                torch.where(self.position_joints, mid - soft * half, -inf),
                torch.where(self.position_joints, mid + soft * half, inf),
            ],
            dim=1,
        )
        self.joint_vel_limits = torch.tensor(layout.velocity_limits, device=dev)
        self._torque_sensors = tuple(f"{j}_torque" for j in layout.joints)
        self._vel_sensors = tuple(f"{j}_vel" for j in layout.joints)
        self.torque_limits = torch.tensor(layout.torque_limits, device=dev)
        self.trunk_id = m.body(go2.TRUNK_BODY).id
        self._sensor_cols: dict[tuple[str, ...], torch.Tensor] = {}
        self._kin_data: mujoco.MjData | None = None

    def _init_buffers(self) -> None:
        n, dev = self.num_envs, self.device
        self.gravity_dir = torch.tensor([0.0, 0.0, -1.0], device=dev).repeat(n, 1)
        """Unit gravity direction per env in the world (= ground) frame: -z on flat ground,
        tilted on a slope (terrain.slope_deg, set_ground_slope)."""
        self.external_slope = False
        """True: the ground slope comes from `set_ground_slope` (evaluation), never drawn."""
        self.actions = torch.zeros(n, self.num_actions, device=dev)
        self.last_actions = torch.zeros_like(self.actions)
        self.latency_steps = torch.zeros(n, dtype=torch.long, device=dev)
        """Physics substeps each env's actuators keep the previous targets (action latency)."""
        self.held_targets = torch.zeros(n, self.num_actions, device=dev)
        """The targets of the previous control step (what a delayed command leaves applied)."""
        self.obs_delay_steps = torch.zeros(n, dtype=torch.long, device=dev)
        """Physics substeps each env's policy observation lags the simulation (observation delay)."""
        for name in ("action_latency_range", "observation_delay_range"):
            lo, hi = getattr(self.cfg.domain_rand, name)
            if not 0.0 <= lo <= hi <= self.dt + 1e-9:
                raise ValueError(
                    f"domain_rand.{name} {(lo, hi)}: need 0 <= low <= high <= the control period {self.dt:g} s"
                )
        if self._obs_delay_on:
            self.sim.keep_substep_states()
        lo, hi = self.cfg.domain_rand.motor_strength_range
        if not 0.0 < lo <= hi:
            raise ValueError(f"domain_rand.motor_strength_range {(lo, hi)}: need 0 < low <= high")
        cmd_cfg = self.cfg.commands
        if cmd_cfg.curriculum_mode == "edge" and cmd_cfg.curriculum_settle_s >= cmd_cfg.resampling_time:
            raise ValueError(
                f"commands.curriculum_settle_s {cmd_cfg.curriculum_settle_s:g} s must be shorter than "
                f"commands.resampling_time {cmd_cfg.resampling_time:g} s, or the edge curriculum judges no step"
            )
        self.commands = torch.zeros(n, 3, device=dev)
        self.episode_length_buf = torch.zeros(n, dtype=torch.long, device=dev)
        self.reset_buf = torch.zeros(n, dtype=torch.bool, device=dev)
        self.time_out_buf = torch.zeros(n, dtype=torch.bool, device=dev)
        self.terminated_buf = torch.zeros(n, dtype=torch.bool, device=dev)
        self.rew_buf = torch.zeros(n, device=dev)
        self.last_joint_vel = torch.zeros(n, self.num_actions, device=dev)
        self.common_step_counter = 0
        self._curriculum_score, self._curriculum_count = 0.0, 0
        # "edge" curriculum: (backward end, forward end) sums of the vx tracking kernel and step counts
        self._edge_score = torch.zeros(2, device=dev)
        self._edge_count = torch.zeros(2, device=dev)
        self.edge_tracking = [float("nan"), float("nan")]
        """The last judged mean vx tracking at the (backward, forward) end ("edge" curriculum)."""
        self.external_commands = False
        """True: commands come from `set_commands` (play, deployment tests), never resampled."""
        self.extras: dict = {"log": {}}
        self.nonfinite_resets = 0
        ranges = self.cfg.commands.ranges
        self.command_ranges = {
            "lin_vel_x": list(ranges.lin_vel_x),
            "lin_vel_y": list(ranges.lin_vel_y),
            "ang_vel_yaw": list(ranges.ang_vel_yaw),
        }
        self._refresh_state()

    def _init_rewards(self) -> None:
        self.reward_terms: dict[str, tuple] = {}
        available = sorted(n[len("_reward_") :] for n in dir(self) if n.startswith("_reward_"))
        for name, scale in self.cfg.rewards.scales.items():
            fn = getattr(self, f"_reward_{name}", None)
            if fn is None:
                raise ValueError(f"unknown reward term {name!r} for {type(self).__name__}; available: {available}")
            if scale != 0.0:
                self.reward_terms[name] = (fn, scale * self.dt)
        self.episode_sums = {name: torch.zeros(self.num_envs, device=self.device) for name in self.reward_terms}

    def _init_observation_layout(self) -> None:
        scales = self.cfg.observations.scales
        self.obs_layout: dict[str, list[tuple[str, int, float]]] = {}
        for group, terms in self.observation_terms().items():
            layout = []
            for term in terms:
                fn = getattr(self, f"_obs_{term}", None)
                if fn is None:
                    raise ValueError(f"{type(self).__name__}: no method _obs_{term} for observation term {term!r}")
                layout.append((term, int(fn().shape[1]), float(scales.get(term, 1.0))))
            self.obs_layout[group] = layout
        nc = self.cfg.noise
        unknown = set(nc.bias) - {term for term, _, _ in self.obs_layout["policy"]}
        if unknown:
            raise ValueError(f"noise.bias names terms the policy does not observe: {sorted(unknown)}")
        noise, bias = [torch.zeros(0)], [torch.zeros(0)]
        for term, dim, scale in self.obs_layout["policy"]:
            amp = nc.scales.get(term, 0.0) * scale * nc.level
            noise.append(torch.full((dim,), amp if nc.enabled else 0.0))
            bias.append(torch.full((dim,), nc.bias.get(term, 0.0) * scale))
        self.noise_vec = torch.cat(noise).to(self.device)
        self.bias_vec = torch.cat(bias).to(self.device)
        self.obs_bias = torch.zeros(self.num_envs, len(self.bias_vec), device=self.device)
        """Each env's constant observation offset this episode (noise.bias, scaled)."""
        self._draw_obs_bias(torch.arange(self.num_envs, device=self.device))  # their reset came before the layout
        self.obs_buf = self.compute_observations()
        self._after_observations()

    def observation_terms(self) -> dict[str, tuple[str, ...]]:
        """Observation group -> term names for this env's config (default: OBSERVATIONS)."""
        return dict(self.OBSERVATIONS)

    def actor_prior(self) -> dict | None:
        """Keyword arguments of a trajectory prior inside the actor (legged_casters.learning.models),
        or None: the actor is a plain MLP."""
        return None

    def policy_obs_slices(self) -> dict[str, list[float]]:
        """Policy observation term -> [start index, scale] in the actor's input (what a
        prior inside the actor reads its terms from)."""
        slices, start = {}, 0
        for name, dim, scale in self.obs_layout["policy"]:
            slices[name] = [start, scale]
            start += dim
        return slices

    def policy_obs_columns(self) -> dict[str, tuple[int, int]]:
        """Policy observation term -> (start, stop) columns in the actor's input."""
        cols, start = {}, 0
        for name, dim, _ in self.obs_layout["policy"]:
            cols[name] = (start, start + dim)
            start += dim
        return cols

    # --- mirror symmetry (legged_casters.learning.symmetry) -------------------------------
    def action_mirror(self) -> tuple[list[int], list[float]]:
        """(index, sign) of the action's mirror image across the trunk's sagittal plane:
        mirrored[:, k] = sign[k] * action[:, index[k]] (go2.mirror_joint per component)."""
        joints = list(self.layout.joints)
        pairs = [go2.mirror_joint(j) for j in joints]
        return [joints.index(name) for name, _ in pairs], [sign for _, sign in pairs]

    def observation_mirror(self) -> dict[str, tuple[list[int], list[float]] | None]:
        """Observation term -> (index, sign) of its mirror image, as action_mirror, within the
        term's own columns; None for a term whose mirror image its values do not determine
        (a world-frame vector needs the heading). Terms missing here have none either."""
        legs = go2.mirror_legs()
        joints = self.action_mirror()
        return {
            "commands": ([0, 1, 2], [1.0, -1.0, -1.0]),  # vx, vy, wz
            "ang_vel": ([0, 1, 2], [-1.0, 1.0, -1.0]),  # an axial vector: roll and yaw rates flip
            "projected_gravity": ([0, 1, 2], [1.0, -1.0, 1.0]),
            "ground_gravity": ([0, 1, 2], [1.0, -1.0, 1.0]),
            "base_lin_vel": ([0, 1, 2], [1.0, -1.0, 1.0]),
            "lin_vel": None,  # world frame
            "base_height": ([0], [1.0]),
            "joint_pos": joints,
            "joint_vel": joints,
            "actions": joints,
            "feet_contact": (legs, [1.0] * 4),
            "wheel_contact": (legs, [1.0] * 4),
        }

    def mirror_maps(self) -> dict[str, tuple[torch.Tensor, torch.Tensor] | None]:
        """Observation group -> (index, sign) tensors of the whole group's mirror image, or
        None when one of its terms has none."""
        terms = self.observation_mirror()
        maps: dict[str, tuple[torch.Tensor, torch.Tensor] | None] = {}
        for group, layout in self.obs_layout.items():
            index: list[int] = []
            sign: list[float] = []
            for term, dim, _ in layout:
                spec = terms.get(term)
                if spec is None:
                    index = []
                    break
                if len(spec[0]) != dim or len(spec[1]) != dim or sorted(spec[0]) != list(range(dim)):
                    raise ValueError(f"the mirror of observation term {term!r} must permute its {dim} columns")
                index += [len(sign) + k for k in spec[0]]
                sign += list(spec[1])
            maps[group] = (
                (torch.tensor(index, device=self.device), torch.tensor(sign, device=self.device)) if index else None
            )
        return maps

    def observation_dims(self) -> dict[str, int]:
        return {group: sum(dim for _, dim, _ in layout) for group, layout in self.obs_layout.items()}

    # --- state ------------------------------------------------------------------------
    def _sensor_columns(self, names: tuple[str, ...]) -> torch.Tensor:
        cols = self._sensor_cols.get(names)
        if cols is None:
            slices = [self.sim.sensor_slice(n) for n in names]
            cols = torch.tensor([i for s in slices for i in range(s.start, s.stop)], device=self.device)
            self._sensor_cols[names] = cols
        return cols

    def sensor_values(self, names: tuple[str, ...]) -> torch.Tensor:
        """Named sensors' values side by side, (num_envs, total dim)."""
        return self.sim.sensordata[:, self._sensor_columns(names)].float()

    def positive_power(self) -> torch.Tensor:
        """(num_envs,) W: positive mechanical power of all actuated joints (wheels included),
        sum over joints of max(tau dq, 0), averaged over the last step's physics substeps
        where the backend keeps them (MuJoCo C), else at the step's end: the integrand of
        the paper's mechanical cost of transport."""
        sub = self.sim.substep_sensordata()
        tau = sub[..., self._sensor_columns(self._torque_sensors)]
        dq = sub[..., self._sensor_columns(self._vel_sensors)]
        return (tau * dq).clamp(min=0.0).sum(dim=-1).mean(dim=1).float()

    def contact_found(self, names: tuple[str, ...]) -> torch.Tensor:
        """(num_envs, len(names)) bool: does each contact sensor see a contact?"""
        return self.sensor_values(names).view(self.num_envs, len(names), 4)[..., 0] > 0

    def contact_force(self, names: tuple[str, ...]) -> torch.Tensor:
        """(num_envs, len(names)) net contact force magnitude of each contact sensor."""
        return torch.linalg.norm(self.sensor_values(names).view(self.num_envs, len(names), 4)[..., 1:], dim=-1)

    def _refresh_state(self) -> None:
        # float32 copies: the CPU backend simulates in float64, the env computes in float32.
        self._set_body_state(self.sim.qpos.float(), self.sim.qvel.float())
        self.torques = self.sensor_values(self._torque_sensors)

    BODY_STATE: tuple[str, ...] = (
        "base_pos", "base_height", "base_quat", "base_lin_vel_world", "base_lin_vel", "base_ang_vel",
        "projected_gravity", "ground_gravity", "joint_pos", "joint_vel",
    )  # fmt: skip
    """The attributes _set_body_state derives from qpos and qvel (what an observation delay delays)."""

    def _set_body_state(self, qpos: torch.Tensor, qvel: torch.Tensor) -> None:
        """BODY_STATE from the generalized positions and velocities (float32)."""
        self.base_pos = qpos[:, 0:3]
        self.base_height = self.base_pos[:, 2]
        """Trunk height above the ground under it (the floor, or the terrain course)."""
        if self.course is not None:
            self.base_height = self.base_height - self.course.height_torch(self.base_pos[:, 0])
        self.base_quat = qpos[:, 3:7]
        self.base_lin_vel_world = qvel[:, 0:3]
        self.base_lin_vel = quat_rotate_inverse(self.base_quat, self.base_lin_vel_world)
        # A free joint's angular velocity is in the trunk frame: for the rigid trunk it is
        # what the IMU gyro measures (the imu site is not rotated), the deploy bridge's input.
        self.base_ang_vel = qvel[:, 3:6]
        # What the IMU measures: gravity in the trunk frame (tilted ground included) ...
        self.projected_gravity = quat_rotate_inverse(self.base_quat, self.gravity_dir)
        # ... and the ground's downward normal in the trunk frame: the trunk's tilt from the
        # ground (rewards and terminations). The two differ only on a slope.
        down = torch.tensor([0.0, 0.0, -1.0], device=self.device).expand(self.num_envs, 3)
        self.ground_gravity = quat_rotate_inverse(self.base_quat, down)
        self.joint_pos = qpos[:, self.joint_qadr]
        self.joint_vel = qvel[:, self.joint_dadr]

    @contextlib.contextmanager
    def _observed_body_state(self):
        """BODY_STATE as the policy's sensors saw it, obs_delay_steps substeps before now
        (observation delay; none in an env's first step after a reset), restored on exit."""
        if not self._obs_delay_on:
            yield
            return
        present = {name: getattr(self, name) for name in self.BODY_STATE}
        qpos, qvel = self.sim.delayed_state(torch.where(self.episode_length_buf > 0, self.obs_delay_steps, 0))
        self._set_body_state(qpos.float(), qvel.float())
        try:
            yield
        finally:
            for name, value in present.items():
                setattr(self, name, value)

    # --- stepping ---------------------------------------------------------------------
    def get_observations(self) -> TensorDict:
        return self.obs_buf

    def step(self, actions: torch.Tensor):
        if self.backend_kind != "cpu" or self.device.type != "cpu":
            return self._step(actions)
        # The rollout thread pool owns the cores. torch's own worker threads, woken by
        # the env's small tensor ops, spin afterwards and slow the physics (measured on
        # 2 cores at 1024 envs: 0.50 s -> 0.19 s per step with one torch thread).
        threads = torch.get_num_threads()
        torch.set_num_threads(1)
        try:
            return self._step(actions)
        finally:
            torch.set_num_threads(threads)

    def _step(self, actions: torch.Tensor):
        clip = self.cfg.control.clip_actions
        actions = actions.to(self.device)
        bad_actions = ~torch.isfinite(actions).all(dim=1)
        self.actions[:] = torch.nan_to_num(actions, nan=0.0, posinf=0.0, neginf=0.0).clamp(-clip, clip)
        targets = self.action_targets(self.actions)
        self._maybe_push()
        if self._latency_on:
            self.sim.step(targets, self.held_targets, self.latency_steps)
            self.held_targets[:] = targets
        else:
            self.sim.step(targets)
        self.episode_length_buf += 1
        self.common_step_counter += 1
        self._refresh_state()
        self._post_physics_step()
        self._resample_on_timer()
        self.check_termination(bad_actions)
        self.compute_reward()
        self._score_edges()
        env_ids = self.reset_buf.nonzero(as_tuple=False).flatten()
        self.extras = {"log": {}}
        if len(env_ids):
            self.reset_idx(env_ids)
        self._advance_curriculum()
        self.obs_buf = self.compute_observations()
        self._after_observations()
        self.last_actions[:] = self.actions
        self.last_joint_vel[:] = self.joint_vel
        self.extras["time_outs"] = self.time_out_buf.clone()
        return self.obs_buf, self.rew_buf.clone(), self.reset_buf.clone(), self.extras

    def action_targets(self, actions: torch.Tensor) -> torch.Tensor:
        """Actuator controls for `actions`: joint angles (rad) for position joints,
        wheel rates (rad/s) for velocity joints."""
        return self.default_joint_pos + self.action_scales * actions

    def _after_observations(self) -> None:
        """Task hook: after each step's observation (e.g. to record a history)."""

    def _init_task_buffers(self) -> None:
        """Task hook: allocate the task's own per-env state (before the first reset)."""

    def _post_physics_step(self) -> None:
        """Task hook: update task state after physics, before terminations and rewards."""

    def set_commands(self, commands: torch.Tensor | list[float]) -> None:
        """Command (vx, vy, wz) for all envs, or (num_envs, 3); switches off resampling."""
        self.external_commands = True
        self.commands[:] = torch.as_tensor(commands, dtype=torch.float32, device=self.device)

    def _resample_on_timer(self) -> None:
        if self.external_commands:
            return
        every = max(1, int(round(self.cfg.commands.resampling_time / self.dt)))
        ids = ((self.episode_length_buf % every) == 0).nonzero(as_tuple=False).flatten()
        if len(ids):
            self.resample_commands(ids)

    def resample_commands(self, env_ids: torch.Tensor) -> None:
        n = len(env_ids)
        previous = self.commands[env_ids].clone()
        for col, key in enumerate(("lin_vel_x", "lin_vel_y", "ang_vel_yaw")):
            lo, hi = self.command_ranges[key]
            self.commands[env_ids, col] = _uniform(lo, hi, (n,), self.device)
        single = torch.rand(n, device=self.device) < self.cfg.commands.single_axis_fraction
        if single.any():
            keep = torch.randint(3, (int(single.sum()),), device=self.device)
            mask = torch.nn.functional.one_hot(keep, 3).to(self.commands.dtype)
            self.commands[env_ids[single]] *= mask
        reverse = torch.rand(n, device=self.device) < self.cfg.commands.reverse_fraction
        if reverse.any():
            self.commands[env_ids[reverse], 0:2] = -previous[reverse, 0:2]
            self.commands[env_ids[reverse], 2] = previous[reverse, 2]
        standing = torch.rand(n, device=self.device) < self.cfg.commands.standing_fraction
        self.commands[env_ids[standing & ~reverse]] = 0.0

    def _maybe_push(self) -> None:
        dr = self.cfg.domain_rand
        every = max(1, int(round(dr.push_interval_s / self.dt)))
        if not dr.push_robots or self.common_step_counter == 0 or self.common_step_counter % every:
            return
        qvel = self.sim.qvel.clone()
        qvel[:, 0:2] += _uniform(-dr.max_push_vel_xy, dr.max_push_vel_xy, (self.num_envs, 2), self.device)
        self.sim.reset(None, self.sim.qpos.clone(), qvel)

    def check_termination(self, bad_actions: torch.Tensor | None = None) -> None:
        term = self.cfg.termination
        terminated = torch.zeros(self.num_envs, dtype=torch.bool, device=self.device)
        if term.trunk_contact:
            terminated |= self.contact_found(("trunk_contact",))[:, 0]
        if term.max_tilt_deg is not None:
            terminated |= self.ground_gravity[:, 2] > -math.cos(math.radians(term.max_tilt_deg))
        # A simulation that blew up, or a policy that produced NaN/inf, ends the episode
        # (counted in the log) instead of poisoning the batch.
        nonfinite = ~(torch.isfinite(self.sim.qpos).all(1) & torch.isfinite(self.sim.qvel).all(1))
        if bad_actions is not None:
            nonfinite |= bad_actions
        self.nonfinite_resets += int(nonfinite.sum())
        self.terminated_buf = terminated | nonfinite
        self.time_out_buf = (self.episode_length_buf >= self.max_episode_length) & ~self.terminated_buf
        self.reset_buf = self.terminated_buf | self.time_out_buf

    def compute_reward(self) -> None:
        self.rew_buf[:] = 0.0
        for name, (fn, scale) in self.reward_terms.items():
            if name == "termination":
                continue
            value = torch.nan_to_num(fn(), nan=0.0, posinf=0.0, neginf=0.0) * scale
            self.rew_buf += value
            self.episode_sums[name] += value
        if self.cfg.rewards.only_positive_rewards:
            self.rew_buf.clamp_(min=0.0)
        if "termination" in self.reward_terms:
            fn, scale = self.reward_terms["termination"]
            value = fn() * scale
            self.rew_buf += value
            self.episode_sums["termination"] += value

    # --- resets -----------------------------------------------------------------------
    def reset_idx(self, env_ids: torch.Tensor) -> None:
        if len(env_ids) == 0:
            return
        self._log_episodes(env_ids)
        self.update_curriculum(env_ids)
        self.randomize(env_ids)
        n = len(env_ids)
        qpos = self.nominal_qpos.expand(n, -1).clone()
        init = self.cfg.init_state
        noise = _uniform(-init.joint_pos_noise, init.joint_pos_noise, (n, self.num_actions), self.device)
        qpos[:, self.joint_qadr] += noise * self.position_joints
        if init.random_yaw:
            qpos[:, 3:7] = quat_from_yaw(_uniform(-math.pi, math.pi, (n,), self.device))
        t = self.cfg.terrain
        if self.course is not None and t.spawn_on_course:
            qpos[:, 0] = _uniform(0.0, self.course.end + 2.0, (n,), self.device)
            qpos[:, 1] = _uniform(-(t.width / 2 - 1.0), t.width / 2 - 1.0, (n,), self.device)
        if self.spawn_x is not None:
            x = self.spawn_x.to(qpos)[env_ids]
            qpos[:, 0] = torch.where(torch.isnan(x), qpos[:, 0], x)
        self._lift_to_floor(qpos)
        qvel = torch.zeros(n, self.model.nv, device=self.device)
        qvel[:, 0:6] = _uniform(-init.base_vel_noise, init.base_vel_noise, (n, 6), self.device)
        self.sim.reset(env_ids, qpos, qvel)
        if not self.external_commands:
            self.resample_commands(env_ids)
        self.actions[env_ids] = 0.0
        self.last_actions[env_ids] = 0.0
        self.last_joint_vel[env_ids] = 0.0
        self.episode_length_buf[env_ids] = 0
        self._reset_task_state(env_ids)
        self._refresh_state()

    def _lift_to_floor(self, qpos: torch.Tensor) -> None:
        """Raise each reset robot so its lowest foot just touches the floor.

        Perturbed joints would otherwise push feet into the floor, and the stiff
        contact the casters need turns even a centimetre of penetration into an
        explosion. MuJoCo C kinematics on the CPU: ~20 us per env.
        """
        if self._kin_data is None:
            self._kin_data = mujoco.MjData(self.model)
        data, q = self._kin_data, qpos.detach().cpu().double().numpy()
        for i in range(len(q)):
            data.qpos[:] = q[i]
            mujoco.mj_kinematics(self.model, data)
            q[i, 2] -= build.ground_clearance(self.model, data, self.cfg.robot)
        if self.course is not None:  # on the course: the ground under the trunk, plus what a slope adds
            ground = self.course.height(q[:, 0])
            q[:, 2] += ground + np.where(ground > 0, 0.03, 0.0)
        qpos[:, 2] = torch.from_numpy(q[:, 2]).to(qpos)

    def _reset_task_state(self, env_ids: torch.Tensor) -> None:
        """Task hook: clear the task's own per-env state."""

    def reset(self) -> TensorDict:
        self.reset_idx(torch.arange(self.num_envs, device=self.device))
        self.obs_buf = self.compute_observations()
        self._after_observations()
        return self.obs_buf

    def _log_episodes(self, env_ids: torch.Tensor) -> None:
        log = self.extras.setdefault("log", {})
        for name, sums in self.episode_sums.items():
            log[f"Episode_Reward/{name}"] = sums[env_ids].mean() / self.cfg.episode_length_s
            sums[env_ids] = 0.0
        log["Curriculum/lin_vel_x_max"] = self.command_ranges["lin_vel_x"][1]
        log["Curriculum/lin_vel_x_min"] = self.command_ranges["lin_vel_x"][0]
        if self.cfg.commands.curriculum and self.cfg.commands.curriculum_mode == "edge":
            for side, value in zip(("backward", "forward"), self.edge_tracking, strict=True):
                if math.isfinite(value):
                    log[f"Curriculum/edge_tracking_{side}"] = value
        log["Diagnostics/nonfinite_resets"] = float(self.nonfinite_resets)

    def update_curriculum(self, env_ids: torch.Tensor) -> None:
        """ "episode" curriculum: collect the linear-tracking score of the episodes ending
        now; once per episode length, widen the forward/backward command range if the
        episodes that ended in that period earned on average more than
        `curriculum_threshold` of the term's maximum. (legged_gym looks only at the envs
        that happen to reset on that exact step.)"""
        cmd = self.cfg.commands
        if not cmd.curriculum or cmd.curriculum_mode != "episode" or "tracking_lin_vel" not in self.reward_terms:
            return
        ran = env_ids[self.episode_length_buf[env_ids] > 0]  # not the initial reset
        self._curriculum_score += float(self.episode_sums["tracking_lin_vel"][ran].sum()) / self.max_episode_length
        self._curriculum_count += len(ran)

    def _score_edges(self) -> None:
        """ "edge" curriculum: add this step's vx tracking of the robots commanded near
        each end of the vx range (within `curriculum_step` of it and at least that far from
        zero), settled for `curriculum_settle_s` after a new command, not ending now."""
        cmd = self.cfg.commands
        if not cmd.curriculum or cmd.curriculum_mode != "edge" or self.external_commands:
            return
        lo, hi = self.command_ranges["lin_vel_x"]
        every = max(1, int(round(cmd.resampling_time / self.dt)))
        settled = (self.episode_length_buf % every) >= int(round(cmd.curriculum_settle_s / self.dt))
        judged = settled & self._edge_eligible() & ~self.terminated_buf
        vx_cmd = self.commands[:, 0]
        kernel = torch.exp(-((vx_cmd - self.base_lin_vel[:, 0]) ** 2) / self.cfg.rewards.tracking_sigma)
        for side, near in enumerate(
            (
                vx_cmd <= min(lo + cmd.curriculum_step, -cmd.curriculum_step),
                vx_cmd >= max(hi - cmd.curriculum_step, cmd.curriculum_step),
            )
        ):
            counted = near & judged
            # where(), not a product: a robot whose state went non-finite must not turn the sum into NaN
            self._edge_score[side] += torch.sum(torch.where(counted, kernel, torch.zeros_like(kernel)))
            self._edge_count[side] += torch.sum(counted)

    def _edge_eligible(self) -> torch.Tensor:
        """Robots the "edge" curriculum judges: those told to move along x alone (a top
        speed is asked for straight ahead, not while turning or sliding sideways)."""
        return (self.commands[:, 1] == 0) & (self.commands[:, 2] == 0)

    def _advance_edges(self) -> None:
        cmd = self.cfg.commands
        score, count = self._edge_score.tolist(), self._edge_count.tolist()
        self._edge_score.zero_()
        self._edge_count.zero_()
        lo, hi = self.command_ranges["lin_vel_x"]
        for side in (0, 1):
            if not count[side]:
                continue
            mean = score[side] / count[side]
            self.edge_tracking[side] = mean
            if not mean > cmd.curriculum_threshold:  # NaN never widens
                continue
            if side == 0:
                lo = max(lo - cmd.curriculum_step, cmd.max_lin_vel_x[0])
            else:
                hi = min(hi + cmd.curriculum_step, cmd.max_lin_vel_x[1])
        self.command_ranges["lin_vel_x"] = [lo, hi]

    def _advance_curriculum(self) -> None:
        cmd = self.cfg.commands
        if not cmd.curriculum or self.common_step_counter % self.max_episode_length:
            return
        if cmd.curriculum_mode == "edge":
            self._advance_edges()
            return
        if not self._curriculum_count:
            return
        _, scale = self.reward_terms["tracking_lin_vel"]
        mean = self._curriculum_score / self._curriculum_count
        self._curriculum_score, self._curriculum_count = 0.0, 0
        if mean > cmd.curriculum_threshold * scale:
            lo, hi = self.command_ranges["lin_vel_x"]
            self.command_ranges["lin_vel_x"] = [
                max(lo - cmd.curriculum_step, cmd.max_lin_vel_x[0]),
                min(hi + cmd.curriculum_step, cmd.max_lin_vel_x[1]),
            ]

    def get_state(self) -> dict:
        """What a resumed run needs besides the policy: the curriculum."""
        return {"command_ranges": {k: list(v) for k, v in self.command_ranges.items()}}

    def set_state(self, state: dict) -> None:
        for key, value in state.get("command_ranges", {}).items():
            if key not in self.command_ranges:
                raise KeyError(f"unknown command range {key!r} in saved env state")
            self.command_ranges[key] = [float(v) for v in value]

    # --- domain randomisation ---------------------------------------------------------
    def _joint_dofs(self, pattern: str) -> list[int]:
        m = self.model
        names = [m.joint(i).name for i in range(m.njnt)]
        dofs = [int(m.jnt_dofadr[i]) for i, name in enumerate(names) if fnmatch.fnmatchcase(name, pattern)]
        if not dofs:
            raise ValueError(f"joint pattern {pattern!r} matches no joint; joints: {names}")
        return dofs

    @property
    def _latency_on(self) -> bool:
        return self.cfg.domain_rand.action_latency_range[1] > 0.0

    @property
    def _obs_delay_on(self) -> bool:
        return self.cfg.domain_rand.observation_delay_range[1] > 0.0

    def _draw_obs_bias(self, env_ids: torch.Tensor) -> None:
        """A new constant observation offset (noise.bias) for these envs; nothing without one
        (no random number is drawn, so runs without a bias keep their random streams)."""
        if self.cfg.noise.bias:
            self.obs_bias[env_ids] = (
                _uniform(-1.0, 1.0, (len(env_ids), len(self.bias_vec)), self.device) * self.bias_vec
            )

    def _draw_substeps(self, seconds: tuple[float, float], n: int) -> torch.Tensor:
        """n delays in whole physics substeps (at most one control step), every count between
        the range's ends (rounded to substeps) equally likely. Rounding a uniform draw in
        seconds instead gave the two ends half the weight of the counts between them: with
        0-20 ms at 5 ms physics, 0 and 20 ms (what evaluate.py checks) were the rarest.
        __init__ refused ranges past the control period, so `hi` is at most `decimation`."""
        lo, hi = (math.floor(t / self.sim.physics_dt + 0.5) for t in seconds)
        return torch.randint(lo, hi + 1, (n,), device=self.device)

    def set_ground_slope(
        self, slope_deg: float | torch.Tensor, downhill_yaw: float | torch.Tensor, env_ids: torch.Tensor | None = None
    ) -> None:
        """Tilt the ground of `env_ids` (None: all) by `slope_deg`, falling towards the world
        yaw `downhill_yaw` (rad; 0: downhill along +x), by tilting gravity; switches off the
        per-episode draw of terrain.slope_deg. Takes effect now and stays over resets."""
        self.external_slope = True
        self._tilt_gravity(torch.arange(self.num_envs, device=self.device) if env_ids is None else env_ids,
                           slope_deg, downhill_yaw)  # fmt: skip
        self._refresh_state()

    def _tilt_gravity(self, env_ids: torch.Tensor, slope_deg, downhill_yaw) -> None:
        n, dev = len(env_ids), self.device
        a = torch.deg2rad(torch.as_tensor(slope_deg, dtype=torch.float32, device=dev).expand(n))
        yaw = torch.as_tensor(downhill_yaw, dtype=torch.float32, device=dev).expand(n)
        g = torch.stack([torch.sin(a) * torch.cos(yaw), torch.sin(a) * torch.sin(yaw), -torch.cos(a)], dim=1)
        self.gravity_dir[env_ids] = g
        self.sim.set_gravity(env_ids, g * float(np.linalg.norm(self.model.opt.gravity)))

    def _draw_slopes(self, env_ids: torch.Tensor) -> None:
        t, n, dev = self.cfg.terrain, len(env_ids), self.device
        slope = _uniform(0.0, t.slope_deg, (n,), dev) * (torch.rand(n, device=dev) < t.slope_fraction)
        self._tilt_gravity(env_ids, slope, _uniform(-math.pi, math.pi, (n,), dev))

    def ground_slope_deg(self) -> torch.Tensor:
        """Each env's ground tilt (deg), (num_envs,)."""
        return torch.rad2deg(torch.acos((-self.gravity_dir[:, 2]).clamp(-1.0, 1.0)))

    def randomize(self, env_ids: torch.Tensor) -> None:
        dr, m, dev, n = self.cfg.domain_rand, self.model, self.device, len(env_ids)
        if self.cfg.terrain.slope_deg > 0.0 and not self.external_slope:
            self._draw_slopes(env_ids)
        if hasattr(self, "obs_bias"):  # not in __init__'s first reset: _init_observation_layout draws it
            self._draw_obs_bias(env_ids)
        if self._latency_on:
            self.latency_steps[env_ids] = self._draw_substeps(dr.action_latency_range, n)
            self.held_targets[env_ids] = self.action_targets(torch.zeros(n, self.num_actions, device=dev))
        if self._obs_delay_on:
            self.obs_delay_steps[env_ids] = self._draw_substeps(dr.observation_delay_range, n)
        if dr.randomize_friction:
            friction = torch.tensor(m.geom_friction, dtype=torch.float32, device=dev).expand(n, -1, -1).clone()
            friction[:, :, 0] = _uniform(*dr.friction_range, (n, 1), dev)
            self.sim.set_model_field("geom_friction", env_ids, friction)
        if dr.randomize_base_mass:
            mass = torch.tensor(m.body_mass, dtype=torch.float32, device=dev).expand(n, -1).clone()
            mass[:, self.trunk_id] += _uniform(*dr.added_mass_range, (n,), dev)
            self.sim.set_model_field("body_mass", env_ids, mass)
        if dr.randomize_com:
            ipos = torch.tensor(m.body_ipos, dtype=torch.float32, device=dev).expand(n, -1, -1).clone()
            ipos[:, self.trunk_id] += _uniform(*dr.com_offset_range, (n, 3), dev)
            self.sim.set_model_field("body_ipos", env_ids, ipos)
        strength_on = tuple(dr.motor_strength_range) != (1.0, 1.0)
        if dr.randomize_gains or strength_on:
            gain = torch.tensor(m.actuator_gainprm, dtype=torch.float32, device=dev).expand(n, -1, -1).clone()
            bias = torch.tensor(m.actuator_biasprm, dtype=torch.float32, device=dev).expand(n, -1, -1).clone()
            kp_scale = kd_scale = torch.ones(n, m.nu, device=dev)
            if dr.randomize_gains:
                kp_scale = _uniform(*dr.kp_scale_range, (n, m.nu), dev)
                kd_scale = _uniform(*dr.kd_scale_range, (n, m.nu), dev)
                # A velocity servo's gain and damping are the same kd (tau = kd (dq* - dq)):
                # one scale for both, or a mismatch would bias its speed.
                kp_scale = torch.where(self.position_joints, kp_scale, kd_scale)
            if strength_on:
                strength = _uniform(*dr.motor_strength_range, (n, m.nu), dev)
                kp_scale, kd_scale = kp_scale * strength, kd_scale * strength
                limit = torch.tensor(m.actuator_forcerange, dtype=torch.float32, device=dev).expand(n, -1, -1)
                self.sim.set_model_field("actuator_forcerange", env_ids, limit * strength.unsqueeze(-1))
            gain[:, :, 0] *= kp_scale
            bias[:, :, 1] *= kp_scale
            bias[:, :, 2] *= kd_scale
            self.sim.set_model_field("actuator_gainprm", env_ids, gain)
            self.sim.set_model_field("actuator_biasprm", env_ids, bias)
        if dr.joint_damping:
            damping = torch.tensor(m.dof_damping, dtype=torch.float32, device=dev).expand(n, -1).clone()
            for pattern, (lo, hi) in dr.joint_damping.items():
                dofs = self._joint_dofs(pattern)
                damping[:, dofs] = _uniform(lo, hi, (n, len(dofs)), dev)
            self.sim.set_model_field("dof_damping", env_ids, damping)
        if dr.joint_frictionloss_scale:
            floss = torch.tensor(m.dof_frictionloss, dtype=torch.float32, device=dev).expand(n, -1).clone()
            for pattern, (lo, hi) in dr.joint_frictionloss_scale.items():
                dofs = self._joint_dofs(pattern)
                floss[:, dofs] *= _uniform(lo, hi, (n, len(dofs)), dev)
            self.sim.set_model_field("dof_frictionloss", env_ids, floss)

    # --- observations -----------------------------------------------------------------
    def compute_observations(self) -> TensorDict:
        clip = self.cfg.observations.clip
        groups = {}
        for group, layout in self.obs_layout.items():
            if group == "policy":
                with self._observed_body_state():
                    parts = [getattr(self, f"_obs_{term}")() * scale for term, _, scale in layout]
            else:
                parts = [getattr(self, f"_obs_{term}")() * scale for term, _, scale in layout]
            obs = torch.cat(parts, dim=1) if parts else torch.zeros(self.num_envs, 0, device=self.device)
            if group == "policy" and self.noise_vec.numel():
                obs = obs + (2 * torch.rand_like(obs) - 1) * self.noise_vec
            if group == "policy" and self.cfg.noise.bias:
                obs = obs + self.obs_bias
            groups[group] = torch.nan_to_num(obs, nan=0.0, posinf=clip, neginf=-clip).clamp(-clip, clip)
        return TensorDict(groups, batch_size=[self.num_envs], device=self.device)

    COMMAND_TERMS: tuple[str, ...] = ("commands", "mode_mask")
    """Observation terms an operator sets (set_commands, set_mode), not the robot's state."""

    def refresh_commands(self, obs: TensorDict) -> TensorDict:
        """`obs` with its COMMAND_TERMS re-read after set_commands / set_mode, the rest as the
        env built it. compute_observations() would re-read proprio_history as well, which
        the env has already advanced with this step's values (it records them right after
        building each observation): the policy would then see this step in the newest slot,
        where training and the bridge have the previous step (zeros at the first)."""
        obs = obs.clone()
        clip = self.cfg.observations.clip
        for group, layout in self.obs_layout.items():
            start = 0
            for term, dim, scale in layout:
                if term in self.COMMAND_TERMS:
                    obs[group][:, start : start + dim] = (getattr(self, f"_obs_{term}")() * scale).clamp(-clip, clip)
                start += dim
        return obs

    def _obs_commands(self) -> torch.Tensor:
        return self.commands

    def _obs_base_lin_vel(self) -> torch.Tensor:
        return self.base_lin_vel

    def _obs_lin_vel(self) -> torch.Tensor:
        """Trunk linear velocity in the world frame."""
        return self.base_lin_vel_world

    def _obs_ang_vel(self) -> torch.Tensor:
        return self.base_ang_vel

    def _obs_projected_gravity(self) -> torch.Tensor:
        return self.projected_gravity

    def _obs_ground_gravity(self) -> torch.Tensor:
        """The ground's downward normal in the trunk frame (unit): with projected_gravity it
        gives the slope under the robot (privileged: a robot's IMU sees only gravity)."""
        return self.ground_gravity

    def _obs_joint_pos(self) -> torch.Tensor:
        """Position joints' angles from the default pose; a wheel's angle says nothing
        (it turns freely), so velocity joints read 0."""
        return (self.joint_pos - self.default_joint_pos) * self.position_joints

    def _obs_joint_vel(self) -> torch.Tensor:
        return self.joint_vel

    def _obs_actions(self) -> torch.Tensor:
        return self.actions

    def _obs_base_height(self) -> torch.Tensor:
        return self.base_height.unsqueeze(1)

    # --- shared reward terms ------------------------------------------------------------
    def _reward_tracking_lin_vel(self) -> torch.Tensor:
        err = torch.sum((self.commands[:, :2] - self.base_lin_vel[:, :2]) ** 2, dim=1)
        return torch.exp(-err / self.cfg.rewards.tracking_sigma)

    def _reward_tracking_ang_vel(self) -> torch.Tensor:
        err = (self.commands[:, 2] - self.base_ang_vel[:, 2]) ** 2
        return torch.exp(-err / self.cfg.rewards.tracking_sigma)

    def _reward_lin_vel_z(self) -> torch.Tensor:
        return self.base_lin_vel[:, 2] ** 2

    def _reward_ang_vel_xy(self) -> torch.Tensor:
        return torch.sum(self.base_ang_vel[:, :2] ** 2, dim=1)

    def _reward_orientation(self) -> torch.Tensor:
        """Trunk tilt from the ground plane: |ground normal's xy in the trunk frame|^2 >= 0."""
        return torch.sum(self.ground_gravity[:, :2] ** 2, dim=1)

    def _reward_base_height(self) -> torch.Tensor:
        return (self.base_height - self.cfg.rewards.base_height_target) ** 2

    def _reward_torques(self) -> torch.Tensor:
        return torch.sum(self.torques**2, dim=1)

    def _reward_joint_vel(self) -> torch.Tensor:
        return torch.sum(self.joint_vel**2, dim=1)

    def _reward_joint_acc(self) -> torch.Tensor:
        return torch.sum(((self.last_joint_vel - self.joint_vel) / self.dt) ** 2, dim=1)

    def _reward_action_rate(self) -> torch.Tensor:
        return torch.sum((self.last_actions - self.actions) ** 2, dim=1)

    def _reward_collision(self) -> torch.Tensor:
        if not self.COLLISION_SENSORS:
            return torch.zeros(self.num_envs, device=self.device)
        return torch.sum(self.contact_force(self.COLLISION_SENSORS) > 0.1, dim=1).float()

    def _reward_termination(self) -> torch.Tensor:
        return (self.terminated_buf & ~self.time_out_buf).float()

    def _reward_joint_pos_limits(self) -> torch.Tensor:
        below = (self.soft_joint_limits[:, 0] - self.joint_pos).clamp(min=0.0)
        above = (self.joint_pos - self.soft_joint_limits[:, 1]).clamp(min=0.0)
        return torch.sum(below + above, dim=1)

    def _reward_joint_vel_limits(self) -> torch.Tensor:
        over = self.joint_vel.abs() - self.cfg.rewards.soft_joint_vel_limit * self.joint_vel_limits
        return torch.sum(over.clamp(min=0.0), dim=1)

    def _reward_torque_limits(self) -> torch.Tensor:
        over = self.torques.abs() - self.cfg.rewards.soft_torque_limit * self.torque_limits
        return torch.sum(over.clamp(min=0.0), dim=1)

    def _reward_stand_still(self) -> torch.Tensor:
        """Sum |q - q0| (rad) >= 0 under a zero command (and, with rewards.stand_still_max_speed,
        only once the trunk moves slower than that): the legs rest when there is nothing to do."""
        still = torch.linalg.norm(self.commands, dim=1) < 0.1
        slow = self.cfg.rewards.stand_still_max_speed
        if slow is not None:
            still = still & (torch.linalg.norm(self.base_lin_vel[:, :2], dim=1) < slow)
        return torch.sum(self._obs_joint_pos().abs(), dim=1) * still

    def close(self) -> None:
        self.sim.close()
