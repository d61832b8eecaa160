"""Write a deliberately simple policy in the export format (policy.yaml + .onnx + .pt).

Used by the tests and the benchmark so they do not depend on the training code. The
policy is affine, ``actions = obs @ W + b``: with the defaults it holds the default
pose (W = 0, b = 0); ``crouch_gain`` g makes the legs fold with the forward command,
action_thigh = g * vx and action_calf = -2 g * vx (targets = default + action_scale *
action): the feet stay under the hips and the trunk lowers (about 3 cm for g = 0.4,
vx = 1), an open-loop response that is easy to check. ``nan_above`` v adds ``0 * sqrt(v - obs[0])``,
which is NaN once the first observation value (vx) exceeds v: a policy that fails on
demand.

    python -m legged_casters.deploy.simple_policy OUT_DIR [--crouch-gain 0.4] [--robot caster]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import onnx
import torch
import yaml
from onnx import TensorProto, helper, numpy_helper

from legged_casters.robot import go2

DEFAULT_TERMS = [
    {"name": "commands", "dim": 3, "scale": 1.0},
    {"name": "mode_mask", "dim": 4, "scale": 1.0},
    {"name": "ang_vel", "dim": 3, "scale": 0.25},
    {"name": "projected_gravity", "dim": 3, "scale": 1.0},
    {"name": "joint_pos", "dim": 12, "scale": 1.0},
    {"name": "joint_vel", "dim": 12, "scale": 0.05},
    {"name": "actions", "dim": 12, "scale": 1.0},
]
PROPULSION_MODES = {"four_wheel": [0, 0, 0, 0], "front_wheel": [0, 0, 1, 1], "rear_wheel": [1, 1, 0, 0]}


class _Affine(torch.nn.Module):
    def __init__(self, w: np.ndarray, b: np.ndarray, nan_above: float | None):
        super().__init__()
        self.w = torch.nn.Parameter(torch.from_numpy(w), requires_grad=False)
        self.b = torch.nn.Parameter(torch.from_numpy(b), requires_grad=False)
        self.nan_above = float("inf") if nan_above is None else float(nan_above)

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        out = obs @ self.w + self.b
        if self.nan_above != float("inf"):
            out = out + 0.0 * torch.sqrt(self.nan_above - obs[:, 0:1])
        return out


def _onnx_model(w: np.ndarray, b: np.ndarray, nan_above: float | None) -> onnx.ModelProto:
    dim = w.shape[0]
    inits = [numpy_helper.from_array(w, "W"), numpy_helper.from_array(b, "B")]
    nodes = [helper.make_node("MatMul", ["obs", "W"], ["xw"]), helper.make_node("Add", ["xw", "B"], ["lin"])]
    out = "lin"
    if nan_above is not None:
        inits += [
            numpy_helper.from_array(np.array([0], np.int64), "s0"),
            numpy_helper.from_array(np.array([1], np.int64), "s1"),
            numpy_helper.from_array(np.array([1], np.int64), "ax"),
            numpy_helper.from_array(np.array(nan_above, np.float32), "thr"),
            numpy_helper.from_array(np.array(0.0, np.float32), "zero"),
        ]
        nodes += [
            helper.make_node("Slice", ["obs", "s0", "s1", "ax"], ["vx"]),
            helper.make_node("Sub", ["thr", "vx"], ["d"]),
            helper.make_node("Sqrt", ["d"], ["r"]),
            helper.make_node("Mul", ["r", "zero"], ["z"]),
            helper.make_node("Add", ["lin", "z"], ["poisoned"]),
        ]
        out = "poisoned"
    nodes.append(helper.make_node("Identity", [out], ["actions"]))
    graph = helper.make_graph(
        nodes,
        "simple_policy",
        [helper.make_tensor_value_info("obs", TensorProto.FLOAT, ["batch", dim])],
        [helper.make_tensor_value_info("actions", TensorProto.FLOAT, ["batch", 12])],
        initializer=inits,
    )
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)])
    model.ir_version = 8
    onnx.checker.check_model(model)
    return model


def write_policy(
    out_dir: str | Path,
    crouch_gain: float = 0.0,
    robot: str = "caster",
    terms: list[dict] | None = None,
    nan_above: float | None = None,
    control_dt: float = 0.02,
    bias: np.ndarray | None = None,
) -> Path:
    """Write policy.yaml, policy.onnx and policy.pt to out_dir; return the yaml path."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    terms = [dict(t) for t in (terms or DEFAULT_TERMS)]
    dim = sum(int(t["dim"]) for t in terms)
    w = np.zeros((dim, 12), np.float32)
    b = np.zeros(12, np.float32) if bias is None else np.asarray(bias, np.float32)
    names = [t["name"] for t in terms]
    if crouch_gain and "commands" in names:
        vx_index = sum(int(t["dim"]) for t in terms[: names.index("commands")])
        for j, joint in enumerate(go2.ACTUATED_JOINTS):
            if "_thigh_" in joint:
                w[vx_index, j] = crouch_gain
            elif "_calf_" in joint:
                w[vx_index, j] = -2.0 * crouch_gain
    onnx.save(_onnx_model(w, b, nan_above), str(out / "policy.onnx"))
    torch.jit.script(_Affine(w, b, nan_above)).save(str(out / "policy.pt"))
    meta = {
        "format_version": 1,
        "task": "simple_test_policy",
        "robot": robot,
        "joint_names": list(go2.ACTUATED_JOINTS),
        "default_joint_pos": go2.default_joint_positions(),
        "action_scale": 0.25,
        "clip_actions": 100.0,
        "kp": go2.kp(),
        "kd": go2.kd(),
        "torque_limits": go2.torque_limits(),
        "joint_pos_limits": [list(r) for r in go2.joint_ranges()],
        "control_dt": control_dt,
        "physics_dt": 0.002,
        "observation": {"dim": dim, "clip": 100.0, "terms": terms},
        "propulsion_modes": PROPULSION_MODES,
        "files": {"onnx": "policy.onnx", "torchscript": "policy.pt"},
        "onnx": {"input": "obs", "output": "actions"},
    }
    path = out / "policy.yaml"
    path.write_text(yaml.safe_dump(meta, sort_keys=False))
    return path


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("out_dir", type=Path)
    p.add_argument("--crouch-gain", type=float, default=0.0)
    p.add_argument("--robot", choices=("caster", "point"), default="caster")
    args = p.parse_args(argv)
    print(write_policy(args.out_dir, args.crouch_gain, args.robot))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
