"""PPO training configuration (rsl-rl-lib 5.5), typed, turned into rsl_rl's dict."""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from typing import Any, Literal

from legged_casters.config import ConfigError
from legged_casters.learning.estimator import TARGET_GROUP
from legged_casters.learning.symmetry import MIRROR_FUNCTION

STAGE_TRAIN_KEY = re.compile(r"^(save_interval|algorithm\.\w+)$")
"""The train config keys a stage (TrainCfg.stages) may set."""


@dataclass
class PolicyCfg:
    actor_hidden_dims: tuple[int, ...] = (512, 256, 128)
    critic_hidden_dims: tuple[int, ...] = (512, 256, 128)
    activation: Literal["elu", "relu", "tanh", "selu", "gelu", "lrelu"] = "elu"
    init_noise_std: float = field(default=1.0, metadata={"min": 0.0})
    learn_noise_std: bool = True
    """Whether PPO may change the exploration std (False: it stays init_noise_std). On casters
    the noise itself propels the robot, so PPO raises a learnt std (research/log.md, "What the curves mean")."""
    noise_std_schedule: tuple[tuple[float, float], ...] = ()
    """(iteration, std) points: before each iteration the exploration std is set to their
    linear interpolation at the number of iterations done (held before the first point and
    after the last), e.g. [[1550, 0.2], [1750, 0.05]]. Needs learn_noise_std false. Empty: off."""
    noise_std_schedule_joints: tuple[str, ...] = ()
    """The action joints whose std the schedule sets: every joint whose name contains one of
    these, e.g. ["thigh", "calf"]; the others keep the std they have. Empty: every joint."""
    noise_correlation: float = field(default=0.0, metadata={"min": 0.0, "max": 0.999})
    """Correlation in time of the exploration noise, per control step: 0 draws white noise
    (rsl_rl's GaussianDistribution); rho > 0 draws it from an AR(1) process with the same
    std (legged_casters.learning.noise), e.g. 0.9 for a time constant of about 10 steps."""
    noise_free_fraction: float = field(default=0.0, metadata={"min": 0.0, "max": 0.9})
    """Share of each process's envs (the last ones) that act with the mean action during the
    rollout, as the deployed actor does, so that PPO's batch and the velocity estimator's
    samples also hold what the noise-free robot does; 0: every env explores."""
    obs_normalization: bool = True
    stop_pose_imitation: float = field(default=0.0, metadata={"min": 0.0})
    """Learning rate of one pass of Adam after each update that pulls the MLP's own mean
    towards the stop pose's action where the pose holds (gait.stop_pitch; PPO gives the MLP
    no gradient there, and the actor hands back to that output when a command comes);
    needs the velocity estimator. 0: off. At 1e-4 it closes the gap and the action spikes at
    the pose's exit within 50-75 iterations, and by 150-200 the network has collapsed into the
    pose (it stops at once and no longer starts); at 1e-3 within 75 (research/log.md, "The
    MLP taught to hold the pose")."""
    critic_history: bool = True
    """Whether the critic's MLP reads the actor's proprioceptive history (it has the privileged state)."""


@dataclass
class PPOCfg:
    num_learning_epochs: int = field(default=5, metadata={"min": 1})
    num_mini_batches: int = field(default=4, metadata={"min": 1})
    clip_param: float = field(default=0.2, metadata={"min": 0.0})
    gamma: float = field(default=0.99, metadata={"min": 0.0, "max": 1.0})
    lam: float = field(default=0.95, metadata={"min": 0.0, "max": 1.0})
    value_loss_coef: float = 1.0
    entropy_coef: float = 0.01
    learning_rate: float = field(default=1e-3, metadata={"min": 0.0})
    max_grad_norm: float = 1.0
    use_clipped_value_loss: bool = True
    schedule: Literal["adaptive", "fixed"] = "adaptive"
    desired_kl: float = 0.01


@dataclass
class EstimatorCfg:
    """The actor's velocity estimator (legged_casters.learning.estimator); off while hidden_dims is empty."""

    hidden_dims: tuple[int, ...] = ()
    actor_history: bool = True
    """Whether the actor's MLP also reads the proprioceptive history (else only the estimator does)."""
    learning_rate: float = field(default=1e-3, metadata={"min": 0.0})
    epochs: int = field(default=2, metadata={"min": 1})
    """Passes of Adam over each rollout, after PPO's update."""
    mini_batches: int = field(default=4, metadata={"min": 1})
    skip_terms: tuple[str, ...] = ()
    """Policy observation terms the estimator does not read (e.g. ["commands"]: an estimate
    that reads the command can learn "the speed is what was asked", which speed feedback
    then cannot tell from the truth)."""


@dataclass
class SymmetryCfg:
    """Left-right mirror symmetry in PPO (legged_casters.learning.symmetry)."""

    mode: Literal["none", "log", "loss", "augment", "both", "exact"] = "none"
    """"loss": a mirror loss on the actor's mean; "augment": every mini-batch also holds the
    mirrored samples (needs mirrorable actor and critic observations); "both"; "log": the
    mirror loss is computed and logged (Loss/symmetry) but not learnt from; "exact": the actor
    and its velocity estimator are symmetric by construction (PriorMLPModel's `mirror`: the
    mean of the output and the mirror of the output for the mirrored observation), trained and
    exported so."""
    mirror_loss_coeff: float = field(default=4.0, metadata={"min": 0.0})
    """Weight of the mirror loss (the mean squared difference of actions, in action units);
    4 as in Yu, Turk and Liu (SIGGRAPH 2018, "Learning Symmetric and Low-Energy Locomotion")."""
    estimator: bool = False
    """The velocity estimator's regression mini-batches also hold the mirror image of each
    sample (observation and target): an estimator that reads sideways speed as evenly to the
    left as to the right. Independent of `mode` (with "none" the actor is trained as without
    it); needs the estimator."""


@dataclass
class TrainCfg:
    experiment_name: str = "default"
    run_name: str = ""
    max_iterations: int = field(default=1500, metadata={"min": 1})
    num_steps_per_env: int = field(default=24, metadata={"min": 1})
    save_interval: int = field(default=50, metadata={"min": 1})
    seed: int = 1
    select_last: int = field(default=0, metadata={"min": 0})
    """After training, rank this many of the newest saved checkpoints by evaluate.py's full
    fixed evaluation (fewest falls, then most checks passed, then the newest) and record the
    first in the run's selected.yaml, which play, evaluate and export then load by default;
    0: none (they load the newest)."""
    policy: PolicyCfg = field(default_factory=PolicyCfg)
    algorithm: PPOCfg = field(default_factory=PPOCfg)
    estimator: EstimatorCfg = field(default_factory=EstimatorCfg)
    symmetry: SymmetryCfg = field(default_factory=SymmetryCfg)
    stages: dict[int, dict[str, Any]] = field(default_factory=dict)
    """Settings that change during the run: {iteration: {key: value}}. From the iteration after
    `iteration` on, each env config key (as `--set` names it) or `train.`-prefixed train config
    key (`train.save_interval`, `train.algorithm.<field>`) takes its value, e.g.
    {800: {"rewards.scales.action_rate": -0.05}, 950: {"train.save_interval": 10}}. At each
    such iteration the run saves model_<iteration>.pt and goes on in the same process with the
    new settings, as a resume would (policy, optimizer, normaliser and curriculum kept). The
    run's env.yaml holds the settings of its first iteration; play, evaluate and export build a
    checkpoint's env with the stages it was trained under. Empty: one setting throughout."""
    env_per_process: dict[str, list[Any]] = field(default_factory=dict)
    """The task's default `train.py --set-per-process`: {env config key: [value of process 0,
    1, ...]}, process r taking entry r modulo the list's length (so a 2-entry list alternates
    over 4 processes). Applies to a new run of two or more processes (`--procs`) for each key
    not given by --set-per-process or --set; one process keeps the env config as it is,
    which is process 0's."""

    def stage_overrides(self, iteration: int) -> tuple[dict[str, Any], dict[str, Any]]:
        """(env overrides, train overrides) of `stages` in force at iteration `iteration`
        (counted from 1): those of every stage that starts before it, later stages winning."""
        env: dict[str, Any] = {}
        train: dict[str, Any] = {}
        for start in sorted(self.stages):
            if start >= iteration:
                break
            for key, value in self.stages[start].items():
                if key.startswith("train."):
                    train[key.removeprefix("train.")] = value
                else:
                    env[key] = value
        return env, train

    def check_stages(self) -> None:
        """Stage iterations positive, and train keys only those a running PPO may change."""
        for start, settings in self.stages.items():
            if start < 1:
                raise ConfigError(f"stages: iteration {start} must be at least 1 (the stage starts after it)")
            if not isinstance(settings, dict) or not settings:
                raise ConfigError(f"stages.{start}: expected a mapping of config keys to values, got {settings!r}")
            for key in settings:
                if key.startswith("train.") and not STAGE_TRAIN_KEY.match(key.removeprefix("train.")):
                    raise ConfigError(
                        f"stages.{start}: {key} cannot change during a run; a stage may set train.save_interval "
                        "and train.algorithm.<field> (networks, seed and schedules are the run's)"
                    )

    def for_env(self, env) -> dict:
        """to_rsl_rl() with what the env says about its actor (prior, observation columns)."""
        self._check_symmetry(env)
        cfg = self.to_rsl_rl(env.actor_prior(), env.policy_obs_columns())
        if self.symmetry.mode == "exact":
            cfg["actor"]["mirror"] = self._actor_mirror(env)
        if self.policy.noise_std_schedule_joints:
            cfg["noise_std_schedule_dims"] = self._scheduled_dims(list(env.layout.joints))
        return cfg

    def _scheduled_dims(self, joints: list[str]) -> list[int]:
        """policy.noise_std_schedule_joints -> the action dimensions the schedule sets."""
        patterns = self.policy.noise_std_schedule_joints
        unknown = [pat for pat in patterns if not any(pat in j for j in joints)]
        if unknown:
            raise ConfigError(f"policy.noise_std_schedule_joints: {unknown} match none of the action joints {joints}")
        return [k for k, j in enumerate(joints) if any(pat in j for pat in patterns)]

    def _check_symmetry(self, env) -> None:
        mode = self.symmetry.mode
        if self.symmetry.estimator and not self.estimator.hidden_dims:
            raise ConfigError(
                "symmetry.estimator=true mirrors the velocity estimator's samples: it needs the estimator "
                "(estimator.hidden_dims)"
            )
        if mode == "exact" and self.symmetry.estimator:
            raise ConfigError(
                "symmetry.mode=exact makes the velocity estimator symmetric itself, so its mirrored samples teach it "
                "nothing more: leave out symmetry.estimator (--train-set symmetry.estimator=false)"
            )
        if mode == "exact" and env.actor_prior() is None:
            raise ConfigError(
                f"symmetry.mode=exact needs an actor with a prior (PriorMLPModel); {type(env).__name__} has none"
            )
        if mode == "none" and not self.symmetry.estimator:
            return
        maps = env.mirror_maps()
        needed = ["policy"] + (["critic"] if mode in ("augment", "both") and "critic" in maps else [])
        if self.symmetry.estimator or (mode == "exact" and self.estimator.hidden_dims):
            needed.append(TARGET_GROUP)
        for group in needed:
            if maps.get(group) is None:
                terms = env.observation_mirror()
                missing = [t for t, _, _ in env.obs_layout[group] if terms.get(t) is None]
                hint = " (symmetry.mode=loss mirrors only the actor's observation)" if group != "policy" else ""
                raise ConfigError(
                    f"symmetry.mode={mode}: the {group!r} observation terms {missing} have no mirror image{hint}"
                )

    def _actor_mirror(self, env) -> dict:
        """symmetry.mode=exact: the mirror maps PriorMLPModel's `mirror` takes, as lists."""
        maps = env.mirror_maps()
        out = {"observation": maps["policy"], "action": env.action_mirror()}
        if self.estimator.hidden_dims:
            out["estimate"] = maps[TARGET_GROUP]
        return {k: [[int(i) for i in index], [float(v) for v in sign]] for k, (index, sign) in out.items()}

    def _noise_std_schedule(self) -> list[list[float]]:
        p = self.policy
        if p.learn_noise_std:
            raise ConfigError(
                "policy.noise_std_schedule sets the exploration std itself: "
                "add --train-set policy.learn_noise_std=false"
            )
        try:
            points = [[float(it), float(std)] for it, std in p.noise_std_schedule]
        except (TypeError, ValueError):
            raise ConfigError(
                f"policy.noise_std_schedule must be [[iteration, std], ...], got {p.noise_std_schedule!r}"
            ) from None
        its = [it for it, _ in points]
        if any(b <= a for a, b in zip(its, its[1:], strict=False)) or any(std <= 0 for _, std in points):
            raise ConfigError(
                f"policy.noise_std_schedule: iterations must increase and every std be positive, got {points}"
            )
        return points

    def to_rsl_rl(self, actor_prior: dict | None = None, obs_columns: dict | None = None) -> dict:
        """The dict OnPolicyRunner expects: actor on "policy", critic on "policy" + "critic".
        `actor_prior` (from env.actor_prior()): the actor adds that trajectory prior to its mean.
        `obs_columns` (env.policy_obs_columns()): needed with the estimator."""
        p = self.policy
        cfg = {
            "num_steps_per_env": self.num_steps_per_env,
            "save_interval": self.save_interval,
            "check_for_nan": True,
            "obs_groups": {"actor": ["policy"], "critic": ["policy", "critic"]},
            "actor": {
                "class_name": "rsl_rl.models.MLPModel",
                "hidden_dims": list(p.actor_hidden_dims),
                "activation": p.activation,
                "obs_normalization": p.obs_normalization,
                "distribution_cfg": {
                    "class_name": "rsl_rl.modules.distribution.GaussianDistribution",
                    "init_std": p.init_noise_std,
                    "learn_std": p.learn_noise_std,
                },
            },
            "critic": {
                "class_name": "rsl_rl.models.MLPModel",
                "hidden_dims": list(p.critic_hidden_dims),
                "activation": p.activation,
                "obs_normalization": p.obs_normalization,
            },
            "algorithm": {"class_name": "rsl_rl.algorithms.PPO", **vars(self.algorithm)},
        }
        if p.noise_correlation > 0.0 or p.noise_free_fraction > 0.0:
            cfg["actor"]["distribution_cfg"].update(
                class_name="legged_casters.learning.noise.CorrelatedGaussianDistribution",
                correlation=p.noise_correlation,
                quiet_fraction=p.noise_free_fraction,
            )
        if p.noise_std_schedule:
            cfg["noise_std_schedule"] = self._noise_std_schedule()
        elif p.noise_std_schedule_joints:
            raise ConfigError("policy.noise_std_schedule_joints needs a policy.noise_std_schedule")
        sym = self.symmetry
        if sym.mode not in ("none", "exact"):  # exact lives in the actor (for_env), not in PPO
            cfg["algorithm"]["symmetry_cfg"] = {
                "data_augmentation_func": MIRROR_FUNCTION,
                "use_data_augmentation": sym.mode in ("augment", "both"),
                "use_mirror_loss": sym.mode in ("loss", "both"),
                "mirror_loss_coeff": sym.mirror_loss_coeff,
            }
        if actor_prior is not None:
            cfg["actor"]["class_name"] = "legged_casters.learning.models.PriorMLPModel"
            cfg["actor"]["prior"] = actor_prior
        history = (obs_columns or {}).get("proprio_history")
        if not p.critic_history and history is not None:
            cfg["critic"]["class_name"] = "legged_casters.learning.models.ColumnsMLPModel"
            cfg["critic"]["drop"] = list(history)
        est = self.estimator
        if est.hidden_dims:
            if actor_prior is None or obs_columns is None:
                raise ValueError("the velocity estimator needs a task with an actor prior and its observation columns")
            if not est.actor_history and history is None:
                raise ValueError("estimator.actor_history=false needs a proprio_history term in the policy observation")
            unknown = [t for t in est.skip_terms if t not in obs_columns]
            if unknown:
                raise ValueError(
                    f"estimator.skip_terms: {unknown} are not policy observation terms; choose from {list(obs_columns)}"
                )
            cfg["actor"]["estimator"] = {
                "hidden_dims": list(est.hidden_dims),
                "out_dim": 3,
                "actor_history": est.actor_history,
                "history_slice": list(history) if history else None,
                "skip_slices": [list(obs_columns[t]) for t in est.skip_terms],
            }
            cfg["algorithm"]["class_name"] = "legged_casters.learning.estimator.EstimatorPPO"
            cfg["algorithm"].update(
                estimator_learning_rate=est.learning_rate,
                estimator_epochs=est.epochs,
                estimator_mini_batches=est.mini_batches,
                estimator_mirror=self.symmetry.estimator,
                pose_imitation_learning_rate=self.policy.stop_pose_imitation,
            )
        elif self.policy.stop_pose_imitation > 0.0:
            raise ConfigError("policy.stop_pose_imitation needs the velocity estimator (estimator.hidden_dims)")
        return cfg
