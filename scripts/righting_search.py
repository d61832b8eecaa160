"""Search the bridge's righting keyframes (legged_casters.deploy.standup.RightingCfg) over simulated falls.

    python scripts/righting_search.py                   # 40 falls to search on, 40 to check on; ~15 min on 2 cores
    python scripts/righting_search.py --falls 10 --check-falls 10 --generations 3 --popsize 8   # a quick try
    python scripts/righting_search.py --check-only      # the shipped keyframes (RightingCfg()) on the check falls

Falls: `scripts/standup_check.py`'s (the shipped caster policy skating at vx 0.5 through the
bridge, pushed over in a random direction, damped 2 s), on the 2 ms robot-side simulator.
Every candidate runs `Righting` (the bridge's own code, on the bridge's control steps)
from each fall's state on the policy's robot model at 2 ms with the export's PD gains and
joint limits, all robots at once on the MuJoCo C backend. Fitness: the share of falls
whose trunk is tilted less than `--ok-tilt` deg when the try ends (where the bridge judges
it), plus half the mean cosine of the tilt over the try's settle time (so that
nearly-righted counts for something). One CMA-ES (`cma`) over the
keyframes (hip, thighs and calf of the lower and upper legs, `RIGHTING_VALUES`) and the
time to each, box-bounded to the Go2's joint ranges. The best candidate is then run on
`--check-falls` other falls (another seed) and printed as a `RightingCfg`.
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
import standup_check  # noqa: E402  (its falls)

from legged_casters.deploy.bridge import SHIPPED_POLICY  # noqa: E402
from legged_casters.deploy.policy import PolicyRunner, gravity_tilt_deg, load_meta, projected_gravity  # noqa: E402
from legged_casters.deploy.standup import RIGHTING_VALUES, Righting, RightingCfg  # noqa: E402
from legged_casters.robot import build  # noqa: E402
from legged_casters.sim.base import physics_model  # noqa: E402
from legged_casters.sim.cpu import CpuBackend  # noqa: E402

BOX = {"hip_out": (-1.0, 1.0), "thigh_front": (-1.5, 3.4), "thigh_rear": (-0.5, 4.5), "calf": (-2.7, -0.85)}
"""Search range (rad) of each keyframe value, inside the Go2's joint ranges."""
DURATION = (0.15, 1.0)
"""Search range (s) of the time to each keyframe."""
NEUTRAL = {"hip_out": 0.0, "thigh_front": 0.8, "thigh_rear": 0.8, "calf": -1.5}
"""The search starts from every keyframe at the default pose."""


def collect_falls(n: int, seed: int, policy: Path) -> tuple[np.ndarray, np.ndarray]:
    """qpos, qvel of `n` robots knocked over as in standup_check.py --falls (righting off)."""
    meta = load_meta(policy)
    runner = PolicyRunner(meta, "onnx")
    rng = np.random.default_rng(seed)
    qpos, qvel = [], []
    while len(qpos) < n:
        chain, force = standup_check.knock_over(meta, runner, "fold", rng, righting=False)
        if force is not None:
            qpos.append(chain.robot.data.qpos.copy())
            qvel.append(chain.robot.data.qvel.copy())
    return np.array(qpos), np.array(qvel)


def to_cfg(x: np.ndarray, keyframes: int) -> RightingCfg:
    """A point of the unit box -> RightingCfg."""
    lo = np.array([BOX[k][0] for k in RIGHTING_VALUES] * 2)
    hi = np.array([BOX[k][1] for k in RIGHTING_VALUES] * 2)
    per = 2 * len(RIGHTING_VALUES)
    frames = tuple(tuple(np.round(lo + x[k * per : (k + 1) * per] * (hi - lo), 3).tolist()) for k in range(keyframes))
    durations = tuple(np.round(DURATION[0] + x[keyframes * per :] * (DURATION[1] - DURATION[0]), 3).tolist())
    return RightingCfg(keyframes=frames, durations=durations)


def start_point(keyframes: int) -> np.ndarray:
    per = [(NEUTRAL[k] - BOX[k][0]) / (BOX[k][1] - BOX[k][0]) for k in RIGHTING_VALUES] * 2
    return np.array(per * keyframes + [0.5] * keyframes)


class Batch:
    """Many robots from given fall states, each running its own RightingCfg as the bridge
    does: the policy's robot model (the robot-side simulators' 2 ms step), the export's PD
    gains and joint limits, the bridge's control period, and the first command at t = one
    period (the bridge's first STANDUP step)."""

    def __init__(self, qpos: np.ndarray, qvel: np.ndarray, copies: int, ok_tilt: float, meta):
        self.model = physics_model(build.build_spec(meta.robot))
        self.names, self.control_dt = list(meta.joint_names), meta.control_dt
        self.decimation = int(round(meta.control_dt / self.model.opt.timestep))
        self.falls = len(qpos)
        self.qadr = [self.model.jnt_qposadr[self.model.joint(n).id] for n in self.names]
        actuators = [self.model.actuator(i).trnid[0] for i in range(self.model.nu)]
        self.act_of_joint = [actuators.index(self.model.joint(n).id) for n in self.names]
        # the model's position servos are the joints' PD: make sure they are the export's gains
        kp = self.model.actuator_gainprm[self.act_of_joint, 0]
        kd = -self.model.actuator_biasprm[self.act_of_joint, 2]
        if not (np.allclose(kp, meta.kp) and np.allclose(kd, meta.kd)):
            raise ValueError(f"the model's servos (kp {kp}, kd {kd}) are not the export's (kp {meta.kp}, kd {meta.kd})")
        self.sim = CpuBackend(self.model, self.falls * copies, self.decimation)
        self.qpos = torch.tensor(np.tile(qpos, (copies, 1)))
        self.qvel = torch.tensor(np.tile(qvel, (copies, 1)))
        self.limits = np.asarray(meta.joint_pos_limits)
        self.ok_tilt = ok_tilt

    def run(self, cfgs: list[RightingCfg]) -> tuple[np.ndarray, np.ndarray]:
        """(ok, upright) per candidate and fall, shape (len(cfgs), falls): upright is the mean
        cosine of the trunk's tilt over the candidate's own settle time (its last keyframe
        held), ok whether the tilt at its end, where the bridge judges it, is under the limit."""
        n = len(cfgs) * self.falls
        if n != self.sim.num_envs:
            raise ValueError(f"{len(cfgs)} candidates need {n} robots; the batch has {self.sim.num_envs}")
        self.sim.reset(slice(None), self.qpos.clone(), self.qvel.clone())
        start = self.sim.qpos[:, self.qadr].numpy().copy()
        side = Righting.side_down(projected_gravity(self.sim.qpos[:, 3:7].numpy()))
        rights = [Righting(self.names, c, self.limits) for c in cfgs]
        # the bridge's k-th STANDUP step (k = 1, 2, ...) sends targets(k * period); the k that
        # reaches the duration judges the tilt of the state it answers
        last = np.array([math.ceil(c.duration / self.control_dt - 1e-9) for c in cfgs]).repeat(self.falls)
        first = np.array([math.ceil((c.duration - c.settle_time) / self.control_dt - 1e-9) for c in cfgs])
        first = first.repeat(self.falls)
        upright, count, judged = np.zeros(n), np.zeros(n), np.zeros(n)
        ctrl = np.zeros((n, self.model.nu))
        for k in range(1, int(last.max()) + 1):
            for i, r in enumerate(rights):
                rows = slice(i * self.falls, (i + 1) * self.falls)
                ctrl[rows, :][:, self.act_of_joint] = r.targets(k * self.control_dt, start[rows], side[rows])
            self.sim.step(torch.from_numpy(ctrl))
            up = -projected_gravity(self.sim.qpos[:, 3:7].numpy())[:, 2]
            window = (k >= first) & (k <= last)
            upright[window] += up[window]
            count[window] += 1
            judged = np.where(k == last, up, judged)
        upright = (upright / np.maximum(count, 1)).reshape(len(cfgs), self.falls)
        ok = judged > math.cos(math.radians(self.ok_tilt))
        return ok.reshape(len(cfgs), self.falls), upright


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--policy", type=Path, default=SHIPPED_POLICY, help="the caster policy that skates before a fall")
    ap.add_argument("--falls", type=int, default=40, help="falls the search runs on")
    ap.add_argument("--check-falls", type=int, default=40, help="other falls the best candidate is checked on")
    ap.add_argument("--keyframes", type=int, default=3)
    ap.add_argument("--generations", type=int, default=40)
    ap.add_argument("--popsize", type=int, default=24)
    ap.add_argument("--sigma", type=float, default=0.25, help="CMA-ES initial step (parameters scaled to [0, 1])")
    ap.add_argument("--ok-tilt", type=float, default=40.0, help="righted: tilt under this (deg) at the end")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--check-only", action="store_true", help="no search: check the shipped keyframes")
    args = ap.parse_args(argv)
    if min(args.falls, args.check_falls, args.keyframes, args.generations) < 1 or args.popsize < 4:
        ap.error("--falls, --check-falls, --keyframes and --generations must be >= 1, --popsize >= 4")
    import cma

    meta = load_meta(args.policy)
    torch.set_num_threads(1)
    t0 = time.time()
    cfg = RightingCfg() if args.check_only else search(args, meta, cma, t0)
    qpos, qvel = collect_falls(args.check_falls, args.seed + 1000, args.policy)
    tilt = gravity_tilt_deg(projected_gravity(qpos[:, 3:7]))
    ok, upright = Batch(qpos, qvel, 1, args.ok_tilt, meta).run([cfg])
    lying = tilt > cfg.start_tilt_deg
    print(
        f"[righting_search] check on {args.check_falls} other falls (seed {args.seed + 1000}): {int(ok.sum())} "
        f"righted; of the {int(lying.sum())} tilted more than {cfg.start_tilt_deg:g} deg (where the bridge rights), "
        f"{int(ok[0][lying].sum())} ({time.time() - t0:.0f} s)",
        flush=True,
    )
    print("RightingCfg(")
    print("    keyframes=(")
    for frame in cfg.keyframes:
        print(f"        {frame},")
    print("    ),")
    print(f"    durations={cfg.durations},")
    print(")")
    return 0


def search(args, meta, cma, t0: float) -> RightingCfg:
    """The CMA-ES; returns the best candidate seen."""
    qpos, qvel = collect_falls(args.falls, args.seed, args.policy)
    tilt = gravity_tilt_deg(projected_gravity(qpos[:, 3:7]))
    print(
        f"[righting_search] {args.falls} falls (seed {args.seed}): {int((tilt > args.ok_tilt).sum())} tilted more "
        f"than {args.ok_tilt:g} deg, {int((tilt > 135).sum())} of them on the back ({time.time() - t0:.0f} s)",
        flush=True,
    )
    batch = Batch(qpos, qvel, args.popsize, args.ok_tilt, meta)
    es = cma.CMAEvolutionStrategy(
        start_point(args.keyframes), args.sigma,
        {"bounds": [0.0, 1.0], "popsize": args.popsize, "seed": args.seed + 1, "verbose": -9},
    )  # fmt: skip
    best = (-math.inf, None)
    for gen in range(args.generations):
        xs = es.ask()
        cfgs = [to_cfg(np.asarray(x), args.keyframes) for x in xs]
        ok, upright = batch.run(cfgs)
        fitness = ok.mean(1) + 0.5 * upright.mean(1)
        es.tell(xs, (-fitness).tolist())
        i = int(np.argmax(fitness))
        if fitness[i] > best[0]:
            best = (float(fitness[i]), cfgs[i])
        print(
            f"[righting_search] gen {gen + 1}/{args.generations}: best of generation {ok[i].mean():.2f} righted "
            f"(fitness {fitness[i]:.3f}), so far {best[0]:.3f} ({time.time() - t0:.0f} s)",
            flush=True,
        )
    return best[1]


if __name__ == "__main__":
    sys.exit(main())
