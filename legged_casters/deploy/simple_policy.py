"""Write a deliberately simple policy in the export format (policy.yaml + .onnx + .pt).

Used by the tests and the benchmark so they do not depend on the training code. The
policy is affine, ``actions = obs @ W + b``: with the defaults it holds the default
pose (W = 0, b = 0); ``crouch_gain`` g makes the legs fold with the forward command,
action_thigh = g * vx and action_calf = -2 g * vx (targets = default + action_scale *
action): the feet stay under the hips and the trunk lowers (about 3 cm for g = 0.4,
vx = 1), an open-loop response that is easy to check. ``gait_gain`` G adds a phase oscillator
that makes the caster robot skate forward: the hips swing left/right in antiphase,
hip_L = -hip_R = x, at ``gait_freq`` (1 Hz) with amplitude G * vx (action units);
the oscillator's state is the previous action (x from FL_hip, its quadrature
component carried, scaled by 0.05, on the calves), rotated by 2 pi f control_dt and
renormalised, so it stops at once when vx = 0. In MuJoCo, G = 0.8 gives about
0.3 m/s at vx = 0.5 and 0.6 m/s at vx = 1. ``nan_above`` v adds ``0 * sqrt(v - obs[0])``,
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


class _Gait:
    """Matrices of the phase oscillator (see the module docstring)."""

    def __init__(self, dim: int, sel: np.ndarray, rot_t: np.ndarray, amp: np.ndarray, out: np.ndarray):
        self.dim, self.sel, self.rot_t, self.amp, self.out = dim, sel, rot_t, amp, out
        self.kick = np.array([0.0, 1e-3], np.float32)


class _Affine(torch.nn.Module):
    def __init__(self, w: np.ndarray, b: np.ndarray, nan_above: float | None, gait: _Gait | None):
        super().__init__()
        self.w = torch.nn.Parameter(torch.from_numpy(w), requires_grad=False)
        self.b = torch.nn.Parameter(torch.from_numpy(b), requires_grad=False)
        self.nan_above = float("inf") if nan_above is None else float(nan_above)
        if gait is None:
            shapes = ((w.shape[0], 2), (2, 2), (w.shape[0], 1), (2, 12))
            gait_or_zero = _Gait(w.shape[0], *[np.zeros(sh, np.float32) for sh in shapes])
        else:
            gait_or_zero = gait
        g = gait_or_zero
        self.has_gait = gait is not None
        self.sel = torch.nn.Parameter(torch.from_numpy(g.sel), requires_grad=False)
        self.rot_t = torch.nn.Parameter(torch.from_numpy(g.rot_t), requires_grad=False)
        self.amp = torch.nn.Parameter(torch.from_numpy(g.amp), requires_grad=False)
        self.out = torch.nn.Parameter(torch.from_numpy(g.out), requires_grad=False)
        self.kick = torch.nn.Parameter(torch.from_numpy(g.kick), requires_grad=False)

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        out = obs @ self.w + self.b
        if self.has_gait:
            v = (obs @ self.sel + self.kick) @ self.rot_t
            u = v / torch.sqrt((v * v).sum(dim=1, keepdim=True) + 1e-12)
            out = out + (u * (obs @ self.amp)) @ self.out
        if self.nan_above != float("inf"):
            out = out + 0.0 * torch.sqrt(self.nan_above - obs[:, 0:1])
        return out


def _onnx_model(w: np.ndarray, b: np.ndarray, nan_above: float | None, gait: _Gait | None) -> onnx.ModelProto:
    dim = w.shape[0]
    inits = [numpy_helper.from_array(w, "W"), numpy_helper.from_array(b, "B")]
    nodes = [helper.make_node("MatMul", ["obs", "W"], ["xw"]), helper.make_node("Add", ["xw", "B"], ["lin"])]
    out = "lin"
    if gait is not None:
        inits += [
            numpy_helper.from_array(gait.sel, "g_sel"),
            numpy_helper.from_array(gait.kick, "g_kick"),
            numpy_helper.from_array(gait.rot_t, "g_rot_t"),
            numpy_helper.from_array(gait.amp, "g_amp"),
            numpy_helper.from_array(gait.out, "g_out"),
            numpy_helper.from_array(np.array([1], np.int64), "g_axis"),
            numpy_helper.from_array(np.array(1e-12, np.float32), "g_eps"),
        ]
        nodes += [
            helper.make_node("MatMul", ["obs", "g_sel"], ["g_p"]),
            helper.make_node("Add", ["g_p", "g_kick"], ["g_pk"]),
            helper.make_node("MatMul", ["g_pk", "g_rot_t"], ["g_v"]),
            helper.make_node("Mul", ["g_v", "g_v"], ["g_v2"]),
            helper.make_node("ReduceSum", ["g_v2", "g_axis"], ["g_n2"], keepdims=1),
            helper.make_node("Add", ["g_n2", "g_eps"], ["g_n2e"]),
            helper.make_node("Sqrt", ["g_n2e"], ["g_n"]),
            helper.make_node("Div", ["g_v", "g_n"], ["g_u"]),
            helper.make_node("MatMul", ["obs", "g_amp"], ["g_a"]),
            helper.make_node("Mul", ["g_u", "g_a"], ["g_ua"]),
            helper.make_node("MatMul", ["g_ua", "g_out"], ["g_o"]),
            helper.make_node("Add", ["lin", "g_o"], ["lin_gait"]),
        ]
        out = "lin_gait"
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
            helper.make_node("Add", [out, "z"], ["poisoned"]),
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


GAIT_CARRIER = 0.05  # the oscillator's second coordinate rides on the calf actions at this scale


def _gait(terms: list[dict], gain: float, freq: float, control_dt: float) -> _Gait:
    names = [t["name"] for t in terms]
    for need in ("commands", "actions"):
        if need not in names:
            raise ValueError(f"the gait policy needs the {need!r} observation term")
    offset = {t["name"]: sum(int(u["dim"]) for u in terms[:i]) for i, t in enumerate(terms)}
    scale = {t["name"]: float(t.get("scale", 1.0)) for t in terms}
    dim = sum(int(t["dim"]) for t in terms)
    j = go2.ACTUATED_JOINTS.index
    sel = np.zeros((dim, 2), np.float32)
    sel[offset["actions"] + j("FL_hip_joint"), 0] = 1.0 / scale["actions"]
    sel[offset["actions"] + j("FL_calf_joint"), 1] = 1.0 / (GAIT_CARRIER * scale["actions"])
    w = 2.0 * np.pi * freq * control_dt
    rot_t = np.array([[np.cos(w), np.sin(w)], [-np.sin(w), np.cos(w)]], np.float32)  # (R p)^T = p^T R^T
    amp = np.zeros((dim, 1), np.float32)
    amp[offset["commands"], 0] = gain / scale["commands"]
    out = np.zeros((2, 12), np.float32)
    for leg in go2.LEGS:
        out[0, j(f"{leg}_hip_joint")] = 1.0 if leg[1] == "L" else -1.0
        out[1, j(f"{leg}_calf_joint")] = GAIT_CARRIER
    return _Gait(dim, sel, rot_t, amp, out)


def write_policy(
    out_dir: str | Path,
    crouch_gain: float = 0.0,
    robot: str = "caster",
    terms: list[dict] | None = None,
    nan_above: float | None = None,
    control_dt: float = 0.02,
    bias: np.ndarray | None = None,
    gait_gain: float = 0.0,
    gait_freq: float = 1.0,
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
    gait = _gait(terms, gait_gain, gait_freq, control_dt) if gait_gain else None
    onnx.save(_onnx_model(w, b, nan_above, gait), str(out / "policy.onnx"))
    torch.jit.script(_Affine(w, b, nan_above, gait)).save(str(out / "policy.pt"))
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
    p.add_argument("--gait-gain", type=float, default=0.0)
    p.add_argument("--robot", choices=("caster", "point"), default="caster")
    args = p.parse_args(argv)
    print(write_policy(args.out_dir, args.crouch_gain, args.robot, gait_gain=args.gait_gain))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
