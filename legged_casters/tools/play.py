"""play.py: run a policy on a few robots with scripted commands; video + plots, or the viewer.

    python play.py --task go2_flat                      # newest checkpoint of the task
    python play.py --profile steps --duration 10        # stand, -0.6 m/s, +0.6 m/s (paper Fig. 6)
    python play.py --policy logs/.../exported/policy.onnx
    python play.py --task caster_omni --policy zero --profile modes
    python play.py --profile constant --mode front_wheel --cmd 0.5 0 0
    python play.py --drive                              # drive it yourself from the keyboard

A task with propulsion modes runs four_wheel (all casters driven) unless --mode says
otherwise; --profile modes steps through 4WD -> FWD -> RWD instead.

Headless (no DISPLAY, or --headless): an mp4 from MuJoCo's offscreen renderer (EGL,
else OSMesa) following robot 0, and PNG plots of robot 0: commanded vs measured vx, vy,
wz; joint angles; for caster tasks the swivel angles and posture errors. With a display
(or --viewer): MuJoCo's passive viewer. Outputs go to <run>/play/ (or --out).

--drive: one robot, the command taken live from the keyboard (keys: legged_casters/deploy/
keyboard.py, docs/driving.md), clamped to the ranges the policy was trained with. With a
display in MuJoCo's desktop viewer; without one (or with --web) in a browser: the page is
served on 127.0.0.1:--port (reach it through an SSH tunnel) unless --host says otherwise.
"""

from __future__ import annotations

import argparse
import math
import os
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from legged_casters.robot import build, go2
from legged_casters.tools import common, render
from legged_casters.tools.common import CheckpointError, UsageError

PROG = "play.py"
PROFILES = ("constant", "steps", "slalom", "modes")
DEFAULT_DURATION = {"constant": 8.0, "steps": 10.0, "slalom": 12.0, "modes": 12.0}
DEFAULT_CMD = (0.5, 0.0, 0.0)
"""The --cmd of the constant, slalom and modes profiles when none is given (vx, vy, wz)."""
MODE_SEQUENCE = (("4WD", (0, 0, 0, 0)), ("FWD", (0, 0, 1, 1)), ("RWD", (1, 1, 0, 0)))
"""4WD -> FWD -> RWD: mode masks (FL, FR, RL, RR), 1 = that caster is not driven."""
DRIVE_HOST = "127.0.0.1"
"""--drive in a browser serves this machine only unless --host says otherwise."""
DEFAULT_MODE = "four_wheel"
"""The propulsion mode of the other profiles on a task with modes (--mode changes it)."""
"""Observation terms that follow the operator: re-read when the command or the mode changes."""


# --- command profiles ----------------------------------------------------------------------------
@dataclass
class Profile:
    name: str
    duration: float
    cmd: tuple[float, float, float]
    mode: tuple[str, tuple[int, ...]] | None = None
    """(name, mask) of every profile but "modes"; None: the task has no propulsion modes."""

    def at(self, t: float) -> tuple[tuple[float, float, float], tuple[str, tuple[int, ...]] | None]:
        """(vx, vy, wz) command and (mode name, mask) or None at time t."""
        vx, vy, wz = self.cmd
        if self.name == "constant":
            return (vx, vy, wz), self.mode
        if self.name == "steps":  # paper Fig. 6: stand ~2 s, backward -0.6 m/s, forward +0.6 m/s
            stand = min(2.0, self.duration / 5)
            if t < stand:
                return (0.0, 0.0, 0.0), self.mode
            half = stand + (self.duration - stand) / 2
            return ((-0.6 if t < half else 0.6), 0.0, 0.0), self.mode
        if self.name == "slalom":  # forward with a lateral command that alternates every 2 s
            side = 1.0 if int(t // 2.0) % 2 == 0 else -1.0
            return (vx, side * 0.4, 0.0), self.mode
        if self.name == "modes":  # the same command through 4WD -> FWD -> RWD
            idx = min(int(t / (self.duration / len(MODE_SEQUENCE))), len(MODE_SEQUENCE) - 1)
            return (vx, vy, wz), MODE_SEQUENCE[idx]
        raise ValueError(self.name)


# --- policies --------------------------------------------------------------------------------------
@dataclass
class PolicySource:
    kind: str  # checkpoint | torchscript | onnx | zero | random
    task: str
    spec: object
    env_cfg: object
    train_cfg: object
    out_dir: Path
    label: str
    selection: common.Selection | None = None
    path: Path | None = None
    obs_dim: int | None = None


def _resolve_source(args: argparse.Namespace, default_log_root: Path | None) -> PolicySource:
    root = common.log_root(args.log_root, default_log_root)
    if args.policy in (None, "checkpoint"):
        try:
            sel = common.select_checkpoint(args, default_log_root)
        except UsageError:
            # No run yet: a new user still sees the project's trained policy skate.
            shipped = (
                None
                if (args.policy or args.load_run or args.checkpoint)
                else common.shipped_policy_dir(common.select_task(args))
            )
            if shipped is None:
                raise
            print(f"[play.py] no training run found: playing the shipped policy {shipped / 'policy.pt'}")
            # under the task its policy.yaml names (the shipped caster_omni: caster_omni_sym)
            args.policy, args.task = str(shipped / "policy.pt"), None
            return _resolve_source(args, default_log_root)
        out = Path(args.out) if args.out else sel.run_dir / "play"
        label = f"{sel.ckpt_path.stem}"
        return PolicySource("checkpoint", sel.task, sel.spec, sel.env_cfg, sel.train_cfg, out, label, selection=sel)
    if args.policy in ("zero", "random"):
        task = common.select_task(args)
        spec = common.check_task(task)
        env_cfg, train_cfg = common.run_configs(spec, None)
        experiment = args.experiment_name or spec.train_cfg.experiment_name
        out = Path(args.out) if args.out else root / experiment / f"play_{args.policy}"
        return PolicySource(args.policy, task, spec, env_cfg, train_cfg, out, args.policy)
    path = Path(args.policy).expanduser()
    if path.is_dir() and (path / "policy.pt").is_file():  # an export folder, as evaluate.py and the bridge take it
        path = path / "policy.pt"
    if path.suffix not in (".pt", ".onnx"):
        raise UsageError(
            f"--policy {args.policy!r}: expected zero, random, an exported policy.pt / policy.onnx or its folder"
        )
    if not path.is_file():
        raise UsageError(f"--policy {path}: no such file")
    if path.suffix == ".pt" and common.is_training_checkpoint(path):
        # A training checkpoint names its run: play it as --load_run <its folder> --checkpoint <it>.
        print(f"[{PROG}] {path} is a training checkpoint: playing it from its run {path.parent}")
        args.policy, args.load_run, args.checkpoint = None, str(path.parent), str(path)
        return _resolve_source(args, default_log_root)
    exp = common.read_export(path, args.task)
    task, spec, env_cfg, train_cfg = exp.task, exp.spec, exp.env_cfg, exp.train_cfg
    if args.out:
        out = Path(args.out)
    elif (path.parent.parent / common.RUN_FILE).is_file():  # <run>/exported/: next to the run's own plays
        out = path.parent.parent / "play"
    else:  # never into the export folder (the thing one copies to a robot, or resources/): one per folder
        out = root / spec.train_cfg.experiment_name / f"play_{path.parent.name}"
    kind = "torchscript" if path.suffix == ".pt" else "onnx"
    return PolicySource(kind, task, spec, env_cfg, train_cfg, out, path.stem, path=path, obs_dim=exp.obs_dim)


def _make_policy(src: PolicySource, env) -> Callable:
    dim = env.observation_dims()["policy"]
    if src.obs_dim is not None and src.obs_dim != dim:
        raise CheckpointError(f"{src.path} expects {src.obs_dim} observations; task {src.task} gives {dim}")
    if src.kind == "checkpoint":
        from legged_casters.tools.export import load_actor

        sel = src.selection
        actor = load_actor(env, sel.train_cfg, sel.ckpt, sel.ckpt_path)
        return lambda obs: actor(obs)
    if src.kind == "torchscript":
        try:
            module = torch.jit.load(str(src.path), map_location="cpu")
        except RuntimeError as err:
            raise CheckpointError(
                f"{src.path} cannot be loaded as an exported TorchScript policy: the file is damaged or was not "
                "written by export.py",
                str(err),
            ) from None
        return lambda obs: module(obs["policy"])
    if src.kind == "onnx":
        import onnxruntime as ort

        try:
            sess = ort.InferenceSession(str(src.path), providers=["CPUExecutionProvider"])
        except Exception as err:
            raise CheckpointError(
                f"{src.path} cannot be loaded as an ONNX policy: the file is damaged or was not written by export.py",
                str(err),
            ) from None
        name = sess.get_inputs()[0].name
        return lambda obs: torch.from_numpy(sess.run(None, {name: obs["policy"].cpu().numpy()})[0])
    if src.kind == "zero":
        return lambda obs: torch.zeros(env.num_envs, env.num_actions)
    gen = torch.Generator().manual_seed(0)
    return lambda obs: torch.rand(env.num_envs, env.num_actions, generator=gen) * 2 - 1


# --- recording and plots ---------------------------------------------------------------------------
class Recorder:
    def __init__(self):
        self.rows: dict[str, list] = {}

    def add(self, **values) -> None:
        for k, v in values.items():
            self.rows.setdefault(k, []).append(np.asarray(v, dtype=np.float64))

    def arrays(self) -> dict[str, np.ndarray]:
        return {k: np.stack(v) for k, v in self.rows.items()}


def _smooth(x: np.ndarray, n: int) -> np.ndarray:
    if n <= 1 or len(x) < n:
        return x
    kernel = np.ones(n) / n
    return np.convolve(np.pad(x, (n // 2, n - 1 - n // 2), mode="edge"), kernel, mode="valid")


def write_plots(data: dict[str, np.ndarray], out: Path, prefix: str, title: str, dt: float) -> list[Path]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    t = data["t"]
    paths = []
    n_avg = max(1, int(round(0.2 / dt)))
    fig, axes = plt.subplots(3, 1, figsize=(9, 7), sharex=True)
    for ax, i, label, unit in zip(axes, range(3), ("vx", "vy", "wz"), ("m/s", "m/s", "rad/s"), strict=True):
        ax.plot(t, data["measured"][:, i], color="tab:blue", alpha=0.3, lw=0.8, label="measured")
        ax.plot(t, _smooth(data["measured"][:, i], n_avg), color="tab:blue", lw=1.5, label="measured (0.2 s mean)")
        ax.plot(t, data["command"][:, i], color="k", ls="--", lw=1.5, label="command")
        ax.set_ylabel(f"{label} [{unit}]")
        ax.grid(alpha=0.3)
    axes[0].legend(loc="upper right", fontsize=8)
    limits = int(data["time_out"].sum())
    falls = int(data["done"].sum()) - limits
    why = [w for w, n in (("fell", falls), ("reached the episode's time limit", limits)) if n]
    resets = f" (grey: robot 0 {' / '.join(why)} and was reset)" if why else ""
    axes[0].set_title(f"{title}: commanded vs measured (trunk frame, robot 0){resets}", fontsize=10)
    axes[-1].set_xlabel("time [s]")
    _mark_modes(axes, data)
    paths.append(_save(fig, out / f"{prefix}_velocity.png"))

    fig, axes = plt.subplots(4, 1, figsize=(9, 9), sharex=True)
    for leg_i, (ax, leg) in enumerate(zip(axes, go2.LEGS, strict=True)):
        for k, kind in enumerate(go2.JOINT_KINDS):
            ax.plot(t, data["joint_pos"][:, 3 * leg_i + k], label=kind)
        ax.set_ylabel(f"{leg} [rad]")
        ax.grid(alpha=0.3)
    axes[0].legend(loc="upper right", fontsize=8, ncol=3)
    axes[0].set_title(f"{title}: actuated joint angles (robot 0)")
    axes[-1].set_xlabel("time [s]")
    _mark_modes(axes, data)
    paths.append(_save(fig, out / f"{prefix}_joints.png"))

    if "phi" in data:
        fig, axes = plt.subplots(4, 1, figsize=(9, 10), sharex=True)
        series = (
            ("phi", data["phi"], "swivel angle phi [rad]"),
            ("cos", np.cos(data["phi"]), "cos(phi)"),
            ("dz", data["theta_diffz"], "theta_diffz [rad]"),
            ("dphi", data["theta_diffphi"], "theta_diffphi [rad]"),
        )
        for ax, (_, values, label) in zip(axes, series, strict=True):
            for leg_i, leg in enumerate(go2.LEGS):
                ax.plot(t, values[:, leg_i], label=leg, lw=1.0)
            ax.set_ylabel(label)
            ax.grid(alpha=0.3)
        axes[0].legend(loc="upper right", fontsize=8, ncol=4)
        axes[0].set_title(f"{title}: casters (robot 0)")
        axes[-1].set_xlabel("time [s]")
        _mark_modes(axes, data)
        paths.append(_save(fig, out / f"{prefix}_casters.png"))
    return paths


def _mark_modes(axes, data) -> None:
    """Dotted red lines where the propulsion mode changes, grey ones where robot 0 was reset."""
    for i in np.nonzero(data["done"] > 0)[0]:
        for ax in axes:
            ax.axvline(data["t"][i], color="0.5", ls="-", lw=2, alpha=0.4)
    if "mode" not in data:
        return
    mode = data["mode"]
    changes = np.nonzero(np.any(np.diff(mode, axis=0) != 0, axis=1))[0]
    for c in changes:
        for ax in axes:
            ax.axvline(data["t"][c + 1], color="tab:red", ls=":", lw=1)


def _save(fig, path: Path) -> Path:
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    import matplotlib.pyplot as plt

    plt.close(fig)
    return path


# --- the command -----------------------------------------------------------------------------------
def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog=PROG,
        description="Run a policy on a few robots with scripted commands: video + plots, or the viewer.",
        formatter_class=common.HelpFormatter,
    )
    common.add_run_selection_flags(p)
    p.add_argument(
        "--policy",
        help="checkpoint (default: from --load_run/--checkpoint), zero, random, or an exported policy.pt/.onnx",
    )
    p.add_argument("--num_envs", type=int, default=2, help="robots (drawn side by side; plots show robot 0)")
    p.add_argument(
        "--profile", choices=PROFILES, help="scripted commands (default: constant with --cmd, steps without)"
    )
    p.add_argument("--duration", type=float, help="seconds (default: constant 8, steps 10, slalom 12, modes 12)")
    p.add_argument(
        "--cmd",
        type=float,
        nargs=3,
        metavar=("VX", "VY", "WZ"),
        help=f"command of the constant profile (vx also for slalom and modes; default {DEFAULT_CMD}); "
        "alone it selects --profile constant",
    )
    p.add_argument(
        "--mode",
        help=f"propulsion mode of a task with modes, e.g. front_wheel (default {DEFAULT_MODE}; "
        "not with --profile modes, which steps through 4WD -> FWD -> RWD)",
    )
    p.add_argument("--sim_backend", choices=("cpu", "warp"), default="cpu", help="play runs on the CPU by default")
    p.add_argument("--headless", action="store_true", help="video + plots even with a display")
    p.add_argument("--viewer", action="store_true", help="MuJoCo's interactive viewer (needs a display)")
    p.add_argument("--no_video", action="store_true", help="headless: write only the plots")
    p.add_argument("--width", type=int, default=640, help="video width in pixels")
    p.add_argument("--height", type=int, default=480, help="video height in pixels")
    p.add_argument("--fps", type=int, default=25, help="video frames per second (real time)")
    p.add_argument("--fast_render", action="store_true", help="no shadows or reflections (~3x faster on a CPU)")
    p.add_argument(
        "--out",
        help="output folder (default: <run>/play; for an export outside a run or the shipped policy: "
        "logs/<experiment>/play_<folder>)",
    )
    g = p.add_argument_group("driving by keyboard (--drive)")
    g.add_argument(
        "--drive",
        action="store_true",
        help="drive one robot from the keyboard: W/S or Up/Down vx, A/D vy, Q/E or Left/Right wz, "
        "1/2/3 propulsion mode, Space stop, R reset; runs until the viewer closes or --duration",
    )
    g.add_argument("--web", action="store_true", help="--drive: the browser viewer even with a display")
    g.add_argument(
        "--host",
        default=DRIVE_HOST,
        help="--drive in a browser: address to serve the page on (default 127.0.0.1, this machine only; "
        "anything else is unsafe: the viewer has no authentication, whoever reaches it drives the robot)",
    )
    g.add_argument(
        "--port", type=int, default=8080, help="--drive in a browser: port of the page (0: the first free from 8080)"
    )
    common.add_env_set_flag(p)
    return p


def resolve_profile(args: argparse.Namespace) -> None:
    """Fill in --profile and --cmd: --cmd alone selects the constant profile, neither the
    steps profile; the steps profile with a --cmd (which it would ignore) is refused."""
    if args.profile is None:
        args.profile = "steps" if args.cmd is None else "constant"
    if args.profile == "steps" and args.cmd is not None:
        raise UsageError(
            "--profile steps runs its own commands (stand, vx -0.6, vx +0.6 m/s) and does not read --cmd; "
            "use --profile constant (or leave --profile out) to hold --cmd"
        )
    if args.cmd is None:
        args.cmd = DEFAULT_CMD


def play(args: argparse.Namespace, default_log_root: Path | None) -> int:
    # --- checks before the simulation starts ------------------------------------------------------
    if args.drive:
        if args.profile is not None or args.cmd is not None or args.mode is not None:
            raise UsageError("--drive takes its command from the keyboard: leave --profile, --cmd and --mode out")
        if args.headless or args.viewer:
            raise UsageError("--drive picks its viewer itself (--web for the browser): leave --headless/--viewer out")
        return drive(args, default_log_root)
    resolve_profile(args)
    if args.num_envs < 1:
        raise UsageError(f"--num_envs must be at least 1, got {args.num_envs}")
    if args.duration is not None and not args.duration > 0:
        raise UsageError(f"--duration must be positive, got {args.duration}")
    if args.viewer and args.headless:
        raise UsageError("--viewer and --headless exclude each other")
    if args.width < 16 or args.height < 16 or args.fps < 1:
        raise UsageError("--width/--height must be at least 16 and --fps at least 1")
    if args.web:
        raise UsageError("--web goes with --drive")
    headless = args.headless or (not args.viewer and not os.environ.get("DISPLAY"))
    if args.viewer and not os.environ.get("DISPLAY"):
        raise UsageError("--viewer needs a display (DISPLAY is not set); leave it out to write a video")
    src = _resolve_source(args, default_log_root)
    if args.profile == "modes" and not hasattr(src.spec.env_class, "set_mode"):
        raise UsageError(f"--profile modes needs a task with propulsion modes (set_mode); {src.task} has none")
    env_cfg = common.eval_env_cfg(src.env_cfg, args.num_envs, args.env_set, args.sim_backend)
    mode = _fixed_mode(args, src, env_cfg)
    gl_backend = None
    if headless and not args.no_video:
        gl_backend, errors = render.probe_gl_backend()
        if gl_backend is None:
            detail = "; ".join(f"{k}: {v}" for k, v in errors.items())
            raise UsageError(f"{render.INSTALL_HINT} ({detail})")
    profile = Profile(args.profile, args.duration or DEFAULT_DURATION[args.profile], tuple(args.cmd), mode)
    _warn_untrained_commands(profile, src)

    # --- simulation --------------------------------------------------------------------------------
    common.limit_cpu_threads(env_cfg.sim.device if args.sim_backend == "warp" else "cpu")
    env = src.spec.env_class(env_cfg)
    try:
        policy = _make_policy(src, env)
        return _run(args, src, env, policy, profile, headless, gl_backend)
    finally:
        env.close()


def _fixed_mode(args: argparse.Namespace, src: PolicySource, env_cfg) -> tuple[str, tuple[int, ...]] | None:
    """(name, mask) of the propulsion mode the profile runs: --mode, else four_wheel, on a
    task with modes (else the env would draw one at random for each robot); None for a
    task without modes and for --profile modes."""
    masks = getattr(getattr(env_cfg, "modes", None), "masks", None)
    if not masks or not hasattr(src.spec.env_class, "set_mode"):
        if args.mode is not None:
            raise UsageError(f"--mode needs a task with propulsion modes; {src.task} has none")
        return None
    if args.profile == "modes":
        if args.mode is not None:
            raise UsageError("--profile modes steps through 4WD -> FWD -> RWD itself: leave --mode out")
        return None
    name = args.mode or DEFAULT_MODE
    if name not in masks:
        raise UsageError(f"--mode {name!r} is not a propulsion mode of {src.task}; known: {', '.join(masks)}")
    return name, tuple(int(x) for x in masks[name])


def _warn_untrained_commands(profile: Profile, src: PolicySource) -> None:
    """Say so when the profile commands more than the task is trained for (e.g. vy for
    the wheel robot, whose axles cannot move it sideways); play it anyway."""
    limits = src.env_cfg.commands.limits()
    worst = [0.0, 0.0, 0.0]
    for k in range(int(profile.duration / 0.1) + 1):
        cmd, _ = profile.at(k * 0.1)
        for a, ((lo, hi), c) in enumerate(zip(limits, cmd, strict=True)):
            if not lo <= c <= hi and abs(c) > abs(worst[a]):
                worst[a] = c
    for a, name in enumerate(("vx", "vy", "wz")):
        if worst[a]:
            lo, hi = limits[a]
            print(
                f"[{PROG}] note: profile {profile.name} commands {name} {worst[a]:+.2f}, outside what {src.task} "
                f"is trained for [{lo:g}, {hi:g}]"
            )


def _apply(env, cmd, mode) -> None:
    env.set_commands(list(cmd))
    if mode is not None:
        env.set_mode(torch.tensor(mode[1], dtype=torch.float32, device=env.device).expand(env.num_envs, 4).clone())


def _run(args, src: PolicySource, env, policy, profile: Profile, headless: bool, gl_backend: str | None) -> int:
    out = src.out_dir
    out.mkdir(parents=True, exist_ok=True)
    prefix = f"{src.label}_{profile.name}"
    title = f"{src.task} ({src.label}), profile {profile.name}"
    dt = env.dt
    steps = int(math.ceil(profile.duration / dt))
    has_caster = hasattr(env, "caster_state")

    cmd, mode = profile.at(0.0)
    _apply(env, cmd, mode)  # external commands first: the reset then keeps them
    obs = env.reset()
    _apply(env, cmd, mode)
    obs = env.refresh_commands(obs)  # the reset's observation: history zeros, as in training

    renderer = writer = viewer = None
    render_model = build.MODEL_FILES[env.cfg.robot]
    frame_every = max(1, int(round(1.0 / (args.fps * dt))))
    video_path = out / f"{prefix}.mp4"
    if headless and gl_backend:
        import imageio.v2 as imageio

        renderer = render.FollowRenderer(
            render_model, gl_backend, args.width, args.height, num_robots=env.num_envs, fast=args.fast_render
        )
        writer = imageio.get_writer(
            str(video_path), fps=1.0 / (frame_every * dt), codec="libx264", quality=7, macro_block_size=8
        )
    elif not headless:
        import mujoco
        import mujoco.viewer

        vmodel = mujoco.MjModel.from_xml_path(str(render_model))
        vdata = mujoco.MjData(vmodel)
        viewer = mujoco.viewer.launch_passive(vmodel, vdata)
        viewer.cam.type = mujoco.mjtCamera.mjCAMERA_TRACKING
        viewer.cam.trackbodyid = vmodel.body(go2.TRUNK_BODY).id
        viewer.cam.distance = 2.0

    rec = Recorder()
    resets, reset_any = 0, False
    wall0 = time.time()
    try:
        for k in range(steps):
            t = k * dt
            new_cmd, new_mode = profile.at(t)
            # Re-apply after a reset too, in case the task draws a new mode for a reset robot.
            if new_cmd != cmd or new_mode != mode or (mode is not None and reset_any):
                cmd, mode = new_cmd, new_mode
                _apply(env, cmd, mode)
                obs = env.refresh_commands(obs)  # the policy sees the new command now
            with torch.no_grad():
                actions = policy(obs)
            obs, _, dones, _ = env.step(actions)
            resets += int(dones[0])
            reset_any = bool(dones.any())
            row = {
                "t": t + dt,
                "command": env.commands[0].cpu().numpy(),
                "measured": np.array(
                    [float(env.base_lin_vel[0, 0]), float(env.base_lin_vel[0, 1]), float(env.base_ang_vel[0, 2])]
                ),
                "joint_pos": env.joint_pos[0].cpu().numpy(),
                "actions": env.actions[0].cpu().numpy(),
                "base_pos": env.base_pos[0].cpu().numpy(),
                "done": float(dones[0]),
                "time_out": float(dones[0] and env.time_out_buf[0]),  # the episode's time limit, not a fall
            }
            if mode is not None:
                row["mode"] = np.asarray(mode[1], dtype=float)
                if isinstance(getattr(env, "mode_mask", None), torch.Tensor):
                    row["env_mode"] = env.mode_mask[0].cpu().numpy()  # what the env actually runs
            if has_caster:
                state = env.caster_state()
                for key in ("phi", "theta_diffz", "theta_diffphi"):
                    row[key] = state[key][0].detach().cpu().numpy()
            rec.add(**row)
            if renderer is not None and k % frame_every == 0:
                c = env.commands[0].tolist()
                text = f"t {t + dt:5.2f} s  cmd vx {c[0]:+.2f} vy {c[1]:+.2f} wz {c[2]:+.2f}"
                if mode is not None:
                    text += f"  {mode[0]}"
                writer.append_data(renderer.render(env.sim.qpos.cpu().double().numpy(), text))
            if viewer is not None:
                if not viewer.is_running():
                    break
                vdata.qpos[:] = env.sim.qpos[0].cpu().double().numpy()
                mujoco.mj_forward(vmodel, vdata)
                viewer.sync()
                time.sleep(max(0.0, wall0 + (k + 1) * dt - time.time()))
    finally:
        if writer is not None:
            writer.close()
        if renderer is not None:
            renderer.close()
        if viewer is not None:
            viewer.close()

    data = rec.arrays()
    np.savez_compressed(out / f"{prefix}_data.npz", **data)
    paths = [*write_plots(data, out, prefix, title, dt), out / f"{prefix}_data.npz"]
    if renderer is not None:
        paths.insert(0, video_path)
    err = np.abs(data["measured"] - data["command"]).mean(axis=0)
    time_limits = int(data["time_out"].sum())
    print(
        f"[{PROG}] {src.task} ({src.label}) profile {profile.name}: {len(data['t'])} steps ({profile.duration:.1f} s "
        f"simulated in {time.time() - wall0:.1f} s), robot 0 resets {resets} "
        f"({resets - time_limits} falls, {time_limits} at the episode's time limit), mean |measured - command| "
        f"vx {err[0]:.3f} vy {err[1]:.3f} wz {err[2]:.3f}"
    )
    for p in paths:
        print(f"[{PROG}] wrote {p}")
    return common.EXIT_OK


# --- driving by keyboard -----------------------------------------------------------------------
def drive(args: argparse.Namespace, default_log_root: Path | None) -> int:
    """--drive: one robot, the command from the keyboard (deploy/keyboard.py), in MuJoCo's
    desktop viewer or, with no display or --web, in a browser."""
    from legged_casters.deploy import protocol as P
    from legged_casters.deploy.drive import CommandRanges
    from legged_casters.deploy.keyboard import HELP, Keyboard

    if args.duration is not None and not args.duration > 0:
        raise UsageError(f"--duration must be positive, got {args.duration}")
    if not 0 <= args.port < 65536:
        raise UsageError(f"--port {args.port}: not a port")
    web = args.web or not os.environ.get("DISPLAY")
    src = _resolve_source(args, default_log_root)
    # one robot, and no episode time limit: it runs until it falls or is reset by hand
    overrides = [*(args.env_set or []), "episode_length_s=1000000.0"]
    env_cfg = common.eval_env_cfg(src.env_cfg, 1, overrides, args.sim_backend)
    ranges = CommandRanges.from_limits(src.env_cfg.commands.limits())
    masks = getattr(getattr(env_cfg, "modes", None), "masks", None) or {}
    if not hasattr(src.spec.env_class, "set_mode"):
        masks = {}
    modes = tuple(m for m in P.PropulsionMode if m.key in masks)
    keys = Keyboard(ranges, modes=modes)
    print(f"[{PROG}] driving {src.task} ({src.label}); command ranges {ranges.describe()}", flush=True)
    print(f"[{PROG}] keys: {HELP}", flush=True)

    common.limit_cpu_threads(env_cfg.sim.device if args.sim_backend == "warp" else "cpu")
    env = src.spec.env_class(env_cfg)
    view = None
    try:
        policy = _make_policy(src, env)
        import mujoco

        from legged_casters.tools import drive_view

        vmodel = mujoco.MjModel.from_xml_path(str(build.MODEL_FILES[env.cfg.robot]))
        trunk = vmodel.body(go2.TRUNK_BODY).id
        if web:
            try:
                view = drive_view.WebDriveView(vmodel, trunk, host=args.host, port=args.port)
            except (RuntimeError, OSError) as err:
                raise UsageError(f"--drive: {err}") from None
            _print_web_help(view, args.host)
        else:
            view = drive_view.DesktopDriveView(vmodel, trunk)
        return _drive_loop(args, env, policy, keys, masks, view)
    finally:
        if view is not None:
            view.close()
        env.close()


def _print_web_help(view, host: str) -> None:
    print(f"[{PROG}] open {view.url} in a browser, click into the page, then drive with the keys", flush=True)
    if host in ("127.0.0.1", "localhost", "::1"):
        print(
            f"[{PROG}] the page is served on this machine only; from another one, tunnel it: "
            f"ssh -L {view.port}:localhost:{view.port} <this machine>, then open http://localhost:{view.port}/",
            flush=True,
        )
    else:
        print(
            f"[{PROG}] warning: serving on {host}: the viewer has no authentication, anyone who reaches "
            "this port sees the robot and drives it",
            flush=True,
        )


def _drive_loop(args, env, policy, keys, masks: dict, view) -> int:
    """Step the policy in real time with the keyboard's command until the viewer closes
    (or --duration); print the command and the measured speed on each change and every 2 s."""

    def mode_of(drive):
        if not masks:
            return None
        key = drive.propulsion.key
        return key, tuple(int(x) for x in masks[key])

    d = keys.drive()
    cmd, mode = (d.vx, d.vy, d.wz), mode_of(d)
    _apply(env, cmd, mode)
    obs = env.reset()
    _apply(env, cmd, mode)
    obs = env.refresh_commands(obs)
    dt = env.dt
    show_every = max(1, int(round(1.0 / (30 * dt))))
    steps = None if args.duration is None else int(math.ceil(args.duration / dt))
    measured = np.zeros(3)
    last_print, k, falls = -math.inf, 0, 0
    wall0 = time.time()
    pace0, k0 = wall0, 0  # real-time pacing: step k is due at pace0 + (k - k0) * dt
    try:
        while view.is_running() and (steps is None or k < steps):
            pressed = view.keys()
            for key in pressed:
                keys.press(key)
            d = keys.drive()
            new_cmd, new_mode = (d.vx, d.vy, d.wz), mode_of(d)
            changed = bool(pressed)
            if d.reset:
                obs = env.reset()
                pace0, k0 = time.time(), k
            if new_cmd != cmd or new_mode != mode or d.reset:
                cmd, mode = new_cmd, new_mode
                _apply(env, cmd, mode)
                obs = env.refresh_commands(obs)  # the policy sees the new command now
                changed = True
            with torch.no_grad():
                actions = policy(obs)
            obs, _, dones, _ = env.step(actions)
            k += 1
            if bool(dones[0]):
                falls += 1
                if mode is not None:
                    _apply(env, cmd, mode)
                    obs = env.refresh_commands(obs)
            v = np.array([float(env.base_lin_vel[0, 0]), float(env.base_lin_vel[0, 1]), float(env.base_ang_vel[0, 2])])
            measured += 0.1 * (v - measured)  # ~0.2 s mean
            c = env.commands[0].tolist()
            state = "STOP (R: reset)" if keys.latch.stopped else (mode[0] if mode else "")
            lines = (
                f"command  vx {c[0]:+.2f}  vy {c[1]:+.2f}  wz {c[2]:+.2f}  {state}",
                f"measured vx {measured[0]:+.2f}  vy {measured[1]:+.2f}  wz {measured[2]:+.2f}",
                "W/S Up/Down vx  A/D vy  Q/E Left/Right wz  1/2/3 mode  Space stop  R reset",
            )
            if changed or k * dt - last_print >= 2.0 or bool(dones[0]):
                last_print = k * dt
                why = f" (keys {' '.join(pressed)})" if pressed else (" (fell: reset)" if bool(dones[0]) else "")
                print(f"[{PROG}] drive t {k * dt:6.1f} s: {lines[0]} | {lines[1]}{why}", flush=True)
            if k % show_every == 0:
                view.show(env.sim.qpos[0].cpu().double().numpy(), lines)
            late = time.time() - (pace0 + (k - k0) * dt)
            if late < 0:
                time.sleep(-late)
            elif late > 0.5:  # slower than real time: do not catch up in a burst
                pace0, k0 = time.time(), k
    except KeyboardInterrupt:
        print(f"\n[{PROG}] stopped")
    print(f"[{PROG}] drove {k * dt:.1f} s simulated in {time.time() - wall0:.1f} s; robot fell {falls} times")
    return common.EXIT_OK


def main(argv: list[str] | None = None, default_log_root: Path | str | None = None) -> int:
    args = build_parser().parse_args(argv)
    return common.run_cli(lambda: play(args, Path(default_log_root) if default_log_root else None), PROG, args.verbose)
