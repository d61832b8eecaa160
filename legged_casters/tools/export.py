"""export.py: a checkpoint's actor as TorchScript and ONNX, plus the deployment description.

    python export.py --task go2_flat                   # newest run of the task
    python export.py --load_run <run> --checkpoint 300 --out exported/

Both networks are the actor's observation normaliser, its MLP, the distribution's mean
and, for a task with a gait prior (caster_omni), the prior added to that mean, all
computed from the one observation vector: obs (batch, dim) -> actions (batch, n), n = 12 or 16 (the wheel robot).

Writes <out>/policy.pt (TorchScript), <out>/policy.onnx (one file, dynamic batch axis),
<out>/policy.yaml, and the run's env.yaml / train.yaml (so that play.py and
scripts/evaluate.py rebuild the task the policy was trained on from the folder alone).
The networks are deterministic. policy.yaml (also in the ONNX metadata_props, key
"policy.yaml") is the one description the robot side reads: joints, gains, periods,
the observation layout, and for caster_omni the gait clock and the history.
"""

from __future__ import annotations

import argparse
import copy
import json
import logging
import sys
import warnings
from pathlib import Path

import mujoco
import numpy as np
import torch
import yaml
from rsl_rl.modules import EmpiricalNormalization
from rsl_rl.utils import resolve_class
from torch import nn

from legged_casters.learning.models import MIRRORED
from legged_casters.learning.symmetry import symmetric_mean, symmetric_pair, with_mirror_image
from legged_casters.robot import go2
from legged_casters.tools import common
from legged_casters.tools.common import CheckpointError, UsageError

PROG = "export.py"
FORMAT_VERSION = 1
PROPULSION_MODES = {"four_wheel": [0, 0, 0, 0], "front_wheel": [0, 0, 1, 1], "rear_wheel": [1, 1, 0, 0]}
"""Mode masks (FL, FR, RL, RR; 1 = that leg's caster is not driven) of tasks with set_mode."""
ONNX_INPUT, ONNX_OUTPUT = "obs", "actions"


class DeployedPolicy(nn.Module):
    """Observation normaliser + actor MLP (+ velocity estimator) (+ gait prior) + deterministic
    head, for TorchScript and ONNX.

    Computes exactly what the training actor computes in its deterministic forward on the
    concatenated policy observation: x = (obs - mean) / (std + eps); with an estimator,
    the MLP reads x's kept columns and the estimate, else x; + prior(obs, estimate) -> head. The
    TorchScript file also has `estimate(obs)`: the estimator's trunk velocity (m/s). A mirrored
    actor (symmetry.mode=exact) runs the observations and their mirror images as one batch and
    averages as it does (legged_casters.learning.symmetry.symmetric_mean)."""

    def __init__(self, actor: nn.Module):
        super().__init__()
        norm = actor.obs_normalizer
        dim = int(actor.obs_dim)
        if isinstance(norm, EmpiricalNormalization):
            mean = norm._mean.detach().reshape(1, dim).clone()
            denom = (norm._std.detach() + norm.eps).reshape(1, dim).clone()
        else:
            mean, denom = torch.zeros(1, dim), torch.ones(1, dim)
        self.register_buffer("obs_mean", mean.float())
        self.register_buffer("obs_denom", denom.float())
        self.mlp = copy.deepcopy(actor.mlp)
        dist = getattr(actor, "distribution", None)
        self.head = dist.as_deterministic_output_module() if dist is not None else nn.Identity()
        self.obs_dim = dim
        self.prior = copy.deepcopy(actor.prior) if hasattr(actor, "prior") else None
        estimator = getattr(actor, "estimator", None)
        self.estimator = copy.deepcopy(estimator) if estimator is not None else None
        columns = actor.mlp_columns.clone() if estimator is not None else torch.zeros(0, dtype=torch.long)
        self.register_buffer("mlp_columns", columns)
        self.mirrored = bool(getattr(actor, "mirrored", False))
        for name in MIRRORED:  # symmetry.mode=exact: the actor's mirror maps (empty where unused)
            for part, dtype in (("index", torch.long), ("sign", torch.float)):
                attr = f"{name}_mirror_{part}"
                value = getattr(actor, attr, None) if self.mirrored else None
                self.register_buffer(attr, value.clone() if value is not None else torch.zeros(0, dtype=dtype))

    def forward(self, observed: torch.Tensor) -> torch.Tensor:
        obs = observed
        if self.mirrored:  # the observations, then their mirror images (PriorMLPModel's mirrored actor)
            obs = with_mirror_image(obs, self.observation_mirror_index, self.observation_mirror_sign)
        x = (obs - self.obs_mean) / self.obs_denom
        estimate = x[:, :0]
        if self.estimator is not None:
            estimate = self.estimator(x)
            if self.mirrored:
                estimate = symmetric_pair(estimate, self.estimate_mirror_index, self.estimate_mirror_sign)
            x = torch.cat([x[:, self.mlp_columns], estimate], dim=-1)
        mean = self.mlp(x)
        if self.prior is not None:
            mean = mean + self.prior(obs, estimate)
        if self.mirrored:
            mean = symmetric_mean(mean, self.action_mirror_index, self.action_mirror_sign)
        if self.prior is not None:  # the stop pose under a zero command, where the prior has one
            mean = self.prior.stop(observed, mean, estimate[: observed.shape[0]])
        return self.head(mean)

    @torch.jit.export
    def estimate(self, obs: torch.Tensor) -> torch.Tensor:
        """The velocity estimator's output (batch, 3): trunk-frame vx, vy, vz in m/s (empty without one)."""
        if self.estimator is None:
            return torch.zeros(obs.shape[0], 0)
        if self.mirrored:
            obs = with_mirror_image(obs, self.observation_mirror_index, self.observation_mirror_sign)
        out = self.estimator((obs - self.obs_mean) / self.obs_denom)
        if self.mirrored:
            out = symmetric_mean(out, self.estimate_mirror_index, self.estimate_mirror_sign)
        return out


def build_actor(env, train_cfg, device: str = "cpu") -> nn.Module:
    """The training actor (rsl_rl model named in the train config) for `env`'s observations."""
    cfg = train_cfg.for_env(env)
    actor_class, actor_cfg = resolve_class(cfg["actor"])
    obs = env.get_observations().to(device)
    return actor_class(obs, cfg["obs_groups"], "actor", env.num_actions, **actor_cfg).to(device)


def load_actor(env, train_cfg, ckpt: dict, ckpt_path: Path, device: str = "cpu") -> nn.Module:
    # policy.noise_free_fraction shapes training rollouts; a loaded actor's rows are scenarios,
    # and one that samples (evaluate/play --stochastic) explores in all of them
    train_cfg = common.with_overrides(train_cfg, {"policy.noise_free_fraction": 0.0}, "load_actor")
    actor = build_actor(env, train_cfg, device)
    try:
        actor.load_state_dict(ckpt["actor_state_dict"], strict=True)
    except RuntimeError as err:
        first = str(err).strip().splitlines()
        raise CheckpointError(
            f"checkpoint {ckpt_path} does not fit the task's actor (obs dims {env.observation_dims()}): "
            + " ".join(first[:3])[:400]
        ) from None
    actor.eval()
    return actor


# --- metadata -------------------------------------------------------------------------------
def _actuator_of_joint(model: mujoco.MjModel) -> dict[str, int]:
    out = {}
    for a in range(model.nu):
        if model.actuator_trntype[a] == mujoco.mjtTrn.mjTRN_JOINT:
            out[model.joint(int(model.actuator_trnid[a, 0])).name] = a
    return out


def propulsion_modes(env) -> dict[str, list[int]]:
    """{name: mask} of a task with propulsion modes (its config's masks), else {}."""
    if not hasattr(env, "set_mode"):
        return {}
    masks = getattr(getattr(env.cfg, "modes", None), "masks", None) or PROPULSION_MODES
    return {str(name): [int(v) for v in mask] for name, mask in masks.items()}


def gait_clock(env) -> dict:
    """{"gait_clock": ...} for a policy that observes the gait clock (and carries the prior), else {}."""
    prior = env.actor_prior()
    if prior is None or prior.get("kind", "gait") != "gait":
        return {}
    return {
        "gait_clock": {
            "frequency": float(prior["cfg"]["frequency"]),
            "phase": "2 pi frequency step control_dt; step counts policy steps from 0 when the policy starts",
            "prior": "the actor adds the skating prior (legged_casters/envs/gait.py) to its output: "
            + ", ".join(f"{k} {v}" for k, v in prior["cfg"].items() if k != "enabled"),
        }
    }


ROBOT_SIDE = "the robot side feeds the observation as for any policy"
"""What policy.yaml's notes say of the parts built into the network (estimator, symmetry)."""


def estimator_spec(actor: nn.Module | None, obs_columns: dict[str, tuple[int, int]] | None = None) -> dict:
    """{"estimator": ...} for an actor with a velocity estimator (inside the network), else {}.
    `obs_columns` (env.policy_obs_columns()) names the observation terms it does not read."""
    if actor is None or getattr(actor, "estimator", None) is None:
        return {}
    read = set(actor.estimator.columns.tolist())
    skipped = [t for t, (a, b) in (obs_columns or {}).items() if not read.intersection(range(a, b))]
    what = "the whole policy observation" + (f" except {', '.join(skipped)}" if skipped else "")
    return {
        "estimator": {
            "output": "base_lin_vel",
            "frame": "trunk, m/s",
            "input": f"{what}, normalised; the actor's MLP reads its output, and so does "
            "the prior where it has speed_feedback",
            "note": f"inside policy.pt / policy.onnx: {ROBOT_SIDE}",
        }
    }


def symmetry_spec(actor: nn.Module | None) -> dict:
    """{"symmetry": ...} for a mirrored actor (symmetry.mode=exact), else {}."""
    if actor is None or not getattr(actor, "mirrored", False):
        return {}
    return {
        "symmetry": {
            "mode": "exact",
            "plane": "the trunk's sagittal plane (left <-> right)",
            "note": "inside policy.pt / policy.onnx: the network averages its action for the observation "
            "with the mirror image of its action for the mirrored observation, so the mirrored "
            f"observation gets exactly the mirrored action; {ROBOT_SIDE}",
        }
    }


def policy_metadata(env, task: str, actor: nn.Module | None = None) -> dict:
    """The deployment description (format_version 1), read from the env and its model."""
    model, cfg = env.model, env.cfg
    act = _actuator_of_joint(model)
    layout = env.layout
    missing = [j for j in layout.joints if j not in act]
    if missing:
        raise UsageError(f"the model has no actuator for joints {missing}")
    ids = [act[j] for j in layout.joints]
    pos = layout.position_mask
    # Position servo: gain kp, bias (0, -kp, -kd); velocity servo: gain kd, bias (0, 0, -kd).
    kp = [float(model.actuator_gainprm[a, 0]) if p else 0.0 for a, p in zip(ids, pos, strict=True)]
    kd = [float(-model.actuator_biasprm[a, 2]) for a in ids]
    torque = [
        float(max(abs(model.actuator_forcerange[a, 0]), abs(model.actuator_forcerange[a, 1])))
        if model.actuator_forcelimited[a]
        else float(lim)
        for a, lim in zip(ids, layout.torque_limits, strict=True)
    ]
    # Position joints: their angle limits; velocity joints: the velocity target's limits.
    ranges = [
        [float(v) for v in (model.joint(j).range if p else r)]
        for j, p, r in zip(layout.joints, pos, layout.ranges, strict=True)
    ]
    terms = [{"name": name, "dim": int(dim), "scale": float(scale)} for name, dim, scale in env.obs_layout["policy"]]
    return {
        "format_version": FORMAT_VERSION,
        "task": task,
        "robot": cfg.robot,
        "joint_names": list(layout.joints),
        "joint_control": list(layout.control),
        "default_joint_pos": [_short(v) for v in env.default_joint_pos.cpu().numpy()],
        "action_scale": float(cfg.control.action_scale),
        **(
            {"velocity_action_scale": float(cfg.control.velocity_action_scale)}
            if go2.CONTROL_VELOCITY in layout.control
            else {}
        ),
        "clip_actions": float(cfg.control.clip_actions),
        "kp": kp,
        "kd": kd,
        "torque_limits": torque,
        "joint_pos_limits": ranges,
        "control_dt": float(env.dt),
        "physics_dt": float(model.opt.timestep),
        "observation": {
            "dim": int(env.observation_dims()["policy"]),
            "clip": float(cfg.observations.clip),
            "terms": terms,
        },
        "propulsion_modes": propulsion_modes(env),
        **gait_clock(env),
        **({"history": env.history_spec()} if getattr(env, "history_spec", lambda: None)() else {}),
        **estimator_spec(actor, env.policy_obs_columns()),
        **symmetry_spec(actor),
        "files": {"onnx": "policy.onnx", "torchscript": "policy.pt"},
        "onnx": {"input": ONNX_INPUT, "output": ONNX_OUTPUT},
    }


def _short(value) -> float:
    """A float32 as the shortest decimal that reads back to it (0.8, not 0.800000011920929)."""
    return float(np.format_float_positional(np.float32(value), unique=True, trim="0"))


class _FlowList(list):
    """Written inline in the YAML: [a, b, c]."""


class _FlowDict(dict):
    """Written inline in the YAML: {a: 1, b: 2}."""


class _MetaDumper(yaml.SafeDumper):
    pass


_MetaDumper.add_representer(_FlowList, lambda d, v: d.represent_sequence("tag:yaml.org,2002:seq", v, flow_style=True))
_MetaDumper.add_representer(
    _FlowDict, lambda d, v: d.represent_mapping("tag:yaml.org,2002:map", v.items(), flow_style=True)
)


def _is_small(value) -> bool:
    """Scalars, and lists / mappings of at most two levels of scalars."""
    if isinstance(value, (list, dict)):
        items = value.values() if isinstance(value, dict) else value
        return all(not isinstance(v, (list, dict)) or all(not isinstance(w, (list, dict)) for w in v) for v in items)
    return True


def _flowed(value, top: bool = True):
    """Inline every list or mapping of scalars (and lists of those), as the schema is written."""
    if isinstance(value, dict):
        if not top and _is_small(value):
            return _FlowDict({k: _flowed(v, False) for k, v in value.items()})
        return {k: _flowed(v, False) for k, v in value.items()}
    if isinstance(value, list) and _is_small(value):
        return _FlowList(_flowed(v, False) for v in value)
    if isinstance(value, list):
        return [_flowed(v, False) for v in value]
    return value


def metadata_yaml(meta: dict) -> str:
    terms = meta["observation"]["terms"]
    body = _flowed({**meta, "observation": {**meta["observation"], "terms": []}})
    body["observation"] = dict(body["observation"])  # a block mapping, terms one per line below
    text = yaml.dump(body, Dumper=_MetaDumper, sort_keys=False, width=1_000_000)
    # Terms one per line as flow mappings, as in the schema.
    lines = "".join(f"  - {{name: {t['name']}, dim: {t['dim']}, scale: {t['scale']!r}}}\n" for t in terms)
    text = text.replace("  terms: []\n", "  terms:\n" + lines)
    assert yaml.safe_load(text) == meta, "metadata YAML does not round-trip"
    return text


# --- writing the files -------------------------------------------------------------------------
def export_policy(actor: nn.Module, meta: dict, out_dir: Path) -> dict[str, Path]:
    """Write policy.pt, policy.onnx and policy.yaml into out_dir; return their paths."""
    import onnx

    out_dir.mkdir(parents=True, exist_ok=True)
    module = DeployedPolicy(actor).cpu().eval()
    dim = module.obs_dim
    if dim != meta["observation"]["dim"]:
        raise CheckpointError(f"actor input {dim} != policy observation dim {meta['observation']['dim']}")
    paths = {name: out_dir / f for name, f in (("torchscript", "policy.pt"), ("onnx", "policy.onnx"))}
    paths["yaml"] = out_dir / "policy.yaml"
    text = metadata_yaml(meta)

    logging.getLogger("torch.onnx").setLevel(logging.ERROR)  # e.g. "torchvision is not installed"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        scripted = torch.jit.script(module)
        extra = {"policy.yaml": text}
        tmp = paths["torchscript"].with_name(".policy.pt.tmp")
        torch.jit.save(scripted, str(tmp), _extra_files=extra)
        tmp.replace(paths["torchscript"])

        example = torch.zeros(2, dim)
        tmp = out_dir / ".policy.onnx.tmp.onnx"
        torch.onnx.export(
            module,
            (example,),
            str(tmp),
            input_names=[ONNX_INPUT],
            output_names=[ONNX_OUTPUT],
            dynamic_shapes=({0: torch.export.Dim("batch")},),
            opset_version=18,
            dynamo=True,
            external_data=False,
            verbose=False,
        )
    proto = onnx.load(str(tmp))
    tmp.unlink()
    for stray in out_dir.glob(".policy.onnx.tmp.onnx*"):
        stray.unlink()
    props = {"policy.yaml": text}
    for key, value in meta.items():
        props[key] = value if isinstance(value, str) else json.dumps(value)
    onnx.helper.set_model_props(proto, props)
    proto.doc_string = (
        f"{meta['task']} policy: {ONNX_INPUT} (batch, {dim}) -> {ONNX_OUTPUT} (batch, {len(meta['joint_names'])})"
    )
    onnx.checker.check_model(proto)
    tmp = out_dir / ".policy.onnx.tmp"
    onnx.save(proto, str(tmp))
    tmp.replace(paths["onnx"])
    common.write_text_atomic(paths["yaml"], text)
    return paths


def check_parity(actor: nn.Module, paths: dict[str, Path], obs: torch.Tensor) -> dict[str, float]:
    """Max |difference| of the TorchScript file and onnxruntime against the training actor on `obs`."""
    import onnxruntime as ort
    from tensordict import TensorDict

    obs = obs.detach().float().cpu()
    with torch.no_grad():
        ref = actor.cpu()(TensorDict({"policy": obs}, batch_size=[obs.shape[0]])).numpy()
        ts = torch.jit.load(str(paths["torchscript"]))(obs).numpy()
    sess = ort.InferenceSession(str(paths["onnx"]), providers=["CPUExecutionProvider"])
    onx = sess.run([ONNX_OUTPUT], {ONNX_INPUT: obs.numpy()})[0]
    return {"torchscript": float(np.abs(ts - ref).max()), "onnx": float(np.abs(onx - ref).max())}


# --- the command -------------------------------------------------------------------------------
def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog=PROG,
        description="Export a checkpoint's actor to TorchScript + ONNX with deployment metadata.",
        formatter_class=common.HelpFormatter,
    )
    common.add_run_selection_flags(p)
    p.add_argument("--out", help="output folder (default: <run>/exported)")
    p.add_argument("--parity_envs", type=int, default=8, help="envs whose observations check the exported files")
    return p


def export(args: argparse.Namespace, default_log_root: Path | None) -> int:
    sel = common.select_checkpoint(args, default_log_root)
    common.limit_cpu_threads("cpu")
    env = common.make_eval_env(sel, num_envs=max(2, args.parity_envs), overrides=[])
    try:
        actor = load_actor(env, sel.train_cfg, sel.ckpt, sel.ckpt_path)
        out = Path(args.out) if args.out else sel.run_dir / "exported"
        meta = policy_metadata(env, sel.task, actor)
        paths = export_policy(actor, meta, out)
        # The run's configs travel with the export: play/evaluate rebuild the task from them.
        from legged_casters.config import dump_yaml

        paths["env_cfg"] = dump_yaml(sel.env_cfg, out / "env.yaml")
        paths["train_cfg"] = dump_yaml(sel.train_cfg, out / "train.yaml")
        # Real observations from a short rollout of the exported policy itself.
        policy = torch.jit.load(str(paths["torchscript"]))
        obs = env.get_observations()["policy"]
        with torch.no_grad():
            for _ in range(10):
                obs = env.step(policy(obs))[0]["policy"]
        err = check_parity(actor, paths, obs)
    finally:
        env.close()
    for name, path in paths.items():
        print(f"[{PROG}] {name:11s} {path}")
    print(
        f"[{PROG}] parity vs training actor on {obs.shape[0]} env observations: "
        + ", ".join(f"{k} {v:.2e}" for k, v in err.items())
    )
    if max(err.values()) > 1e-5:
        print(f"[{PROG}] error: exported policy differs from the training actor by more than 1e-5", file=sys.stderr)
        return common.EXIT_FAILURE
    return common.EXIT_OK


def main(argv: list[str] | None = None, default_log_root: Path | str | None = None) -> int:
    args = build_parser().parse_args(argv)
    return common.run_cli(
        lambda: export(args, Path(default_log_root) if default_log_root else None), PROG, args.verbose
    )
