"""PPO training configuration (rsl-rl-lib 5.5), typed, turned into rsl_rl's dict."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal


@dataclass
class PolicyCfg:
    actor_hidden_dims: tuple[int, ...] = (512, 256, 128)
    critic_hidden_dims: tuple[int, ...] = (512, 256, 128)
    activation: Literal["elu", "relu", "tanh", "selu", "gelu", "lrelu"] = "elu"
    init_noise_std: float = field(default=1.0, metadata={"min": 0.0})
    obs_normalization: bool = True


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
class TrainCfg:
    experiment_name: str = "default"
    run_name: str = ""
    max_iterations: int = field(default=1500, metadata={"min": 1})
    num_steps_per_env: int = field(default=24, metadata={"min": 1})
    save_interval: int = field(default=50, metadata={"min": 1})
    seed: int = 1
    policy: PolicyCfg = field(default_factory=PolicyCfg)
    algorithm: PPOCfg = field(default_factory=PPOCfg)

    def to_rsl_rl(self, actor_prior: dict | None = None) -> dict:
        """The dict OnPolicyRunner expects: actor on "policy", critic on "policy" + "critic".
        `actor_prior` (from env.actor_prior()): the actor adds that trajectory prior to its mean."""
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
        if actor_prior is not None:
            cfg["actor"]["class_name"] = "legged_casters.models.PriorMLPModel"
            cfg["actor"]["prior"] = actor_prior
        return cfg
