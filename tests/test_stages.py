"""Training stages (TrainCfg.stages): settings that change at given iterations of one run, the
run saving, rebuilding and going on as a resume would; and the tools that build a
checkpoint's env with the stages it was trained under."""

from __future__ import annotations

import contextlib
import io
from pathlib import Path

import pytest
import torch

from legged_casters import registry
from legged_casters.config import ConfigError, load_yaml
from legged_casters.envs.go2_flat import Go2FlatEnv
from legged_casters.tools import common, train

TASK = "go2_flat"
STAGES = "stages={1: {rewards.scales.action_rate: -0.5}, 3: {train.save_interval: 1, rewards.scales.action_rate: -0.7}}"
SMALL = [
    "--task", TASK, "--num_envs", "4", "--sim_backend", "cpu", "--console", "line", "--eval_every", "0",
    "--train-set", "num_steps_per_env=8", "--train-set", "save_interval=50",
    "--train-set", "policy.actor_hidden_dims=[16]", "--train-set", "policy.critic_hidden_dims=[16]",
]  # fmt: skip


def _train(root: Path, *extra: str) -> tuple[int, str]:
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        rc = train.main([*SMALL, "--log_root", str(root), *extra])
    return rc, out.getvalue()


@contextlib.contextmanager
def _recording_action_rate():
    """The action-rate weight of every env built inside the block, in order."""
    built: list[float] = []
    original = Go2FlatEnv.__init__

    def record(self, cfg, *args, **kwargs):
        built.append(cfg.rewards.scales["action_rate"])
        original(self, cfg, *args, **kwargs)

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(Go2FlatEnv, "__init__", record)
        yield built


@pytest.fixture(scope="module")
def staged(tmp_path_factory):
    """A 5-iteration run whose action-rate weight changes after iterations 1 and 3 (where it
    also starts saving every iteration), then resumed for one more; the weight of every env
    the runs built, in order."""
    root = tmp_path_factory.mktemp("logs")
    with _recording_action_rate() as built:
        rc, out = _train(root, "--max_iterations", "5", "--train-set", STAGES)
        assert rc == 0, out
        first = list(built)
        (run_dir,) = (root / TASK).iterdir()
        rc, resumed = _train(root, "--resume", "--max_iterations", "1")
        assert rc == 0, resumed
    return run_dir, first, built[len(first) :], out


def test_each_stage_runs_with_its_settings_and_saves_where_it_starts(staged):
    run_dir, built, _, out = staged
    default = registry.task_configs(TASK)[0].rewards.scales["action_rate"]
    assert built == [default, -0.5, -0.7]  # one env per stage, each with the settings in force
    # model_1 and model_3 where a stage starts; from 3 on a checkpoint every iteration (6: the resume's)
    assert [it for it, _ in common.checkpoints(run_dir)] == [1, 3, 4, 5, 6]
    for it, path in common.checkpoints(run_dir):
        assert torch.load(path, weights_only=True)["iter"] + 1 == it
    assert "stage after iteration 1: rewards.scales.action_rate=-0.5" in out
    assert "it 5/5" in out and "it 2/5" in out  # the progress line counts to the run's end, not the stage's
    # env.yaml holds the first iteration's settings, train.yaml the stages
    saved_env = load_yaml(type(registry.get_task(TASK).env_cfg), run_dir / "env.yaml")
    assert saved_env.rewards.scales["action_rate"] == default
    saved_train = load_yaml(type(registry.get_task(TASK).train_cfg), run_dir / "train.yaml")
    assert saved_train.stages[3]["train.save_interval"] == 1


def test_the_policy_goes_on_across_a_stage(staged):
    """A stage continues the run: the iteration count, the optimizer's steps and the
    observation normaliser's count go on, as a resume's would."""
    run_dir, *_ = staged
    one, three = (torch.load(run_dir / f"model_{n}.pt", weights_only=True) for n in (1, 3))
    counts = [ck["actor_state_dict"]["obs_normalizer.count"].item() for ck in (one, three)]
    assert counts[1] > counts[0] > 0
    steps = [next(iter(ck["optimizer_state_dict"]["state"].values()))["step"].item() for ck in (one, three)]
    assert steps[1] > steps[0] > 0


def test_a_resume_takes_the_stage_in_force(staged):
    _, _, built_on_resume, _ = staged
    assert built_on_resume == [-0.7]  # resumed after iteration 5: the stage after 3 holds


def test_a_checkpoint_is_evaluated_with_the_settings_it_was_trained_under(staged):
    run_dir, *_ = staged
    default = registry.task_configs(TASK)[0].rewards.scales["action_rate"]
    weights = {}
    for n in (1, 3, 4):
        args = type("A", (), {"task": TASK, "log_root": str(run_dir.parent.parent), "experiment_name": None})()
        args.load_run, args.checkpoint = str(run_dir), str(n)
        sel = common.select_checkpoint(args, None)
        weights[n] = sel.env_cfg.rewards.scales["action_rate"]
        other = torch.load(run_dir / "model_1.pt", weights_only=True)
        assert sel.env_cfg_for(other).rewards.scales["action_rate"] == default
    # model_1 was trained before the first stage, model_3 in the first, model_4 in the second
    assert weights == {1: default, 3: -0.5, 4: -0.7}


def test_the_command_line_wins_over_a_stage(tmp_path):
    with _recording_action_rate() as built:
        rc, out = _train(
            tmp_path, "--max_iterations", "2", "--train-set", STAGES, "--set", "rewards.scales.action_rate=-0.9"
        )
    assert rc == 0, out
    assert built == [-0.9, -0.9]


@pytest.mark.parametrize(
    "stages, says",
    [
        ("stages={0: {rewards.scales.action_rate: -0.5}}", "at least 1"),
        ("stages={5: {train.seed: 3}}", "cannot change during a run"),
        ("stages={5: {train.policy.actor_hidden_dims: [8]}}", "cannot change during a run"),
        ("stages={5: {rewards.no_such_field: 1}}", "no_such_field"),
    ],
)
def test_a_bad_stage_fails_before_the_simulation(tmp_path, monkeypatch, stages, says):
    def boom(self, cfg):
        raise AssertionError("the simulation was started")

    monkeypatch.setattr(Go2FlatEnv, "__init__", boom)
    err = io.StringIO()
    with contextlib.redirect_stderr(err):
        rc, out = _train(tmp_path, "--max_iterations", "2", "--train-set", stages)
    assert rc == common.EXIT_USAGE, out
    assert says in err.getvalue() + out
    assert not (tmp_path / TASK).exists()  # no run folder left behind


def test_stage_overrides_take_the_latest_value_of_each_key():
    cfg = registry.task_configs(TASK)[1]
    cfg.stages = {10: {"a.b": 1, "train.save_interval": 5}, 20: {"a.b": 2}}
    assert cfg.stage_overrides(10) == ({}, {})
    assert cfg.stage_overrides(11) == ({"a.b": 1}, {"save_interval": 5})
    assert cfg.stage_overrides(21) == ({"a.b": 2}, {"save_interval": 5})
    cfg.stages = {10: {}}
    with pytest.raises(ConfigError, match="expected a mapping"):
        cfg.check_stages()


def test_caster_omni_is_the_shipped_recipe_in_one_run():
    """The default caster task's run is the recipe: its last stage's env is the shipped
    policy's env.yaml in every setting the recipe changes."""
    spec = registry.get_task("caster_omni")
    shipped = load_yaml(type(spec.env_cfg), common.SHIPPED_POLICIES / "caster_omni" / "env.yaml")
    final = common.stage_env_cfg(spec.env_cfg, spec.train_cfg, spec.train_cfg.max_iterations)
    first = common.stage_env_cfg(spec.env_cfg, spec.train_cfg, 1)
    assert first.gait.amplitude_law_backward == [] and first.domain_rand.observation_delay_range[1] == 0.0
    assert final.gait.amplitude_law_backward == shipped.gait.amplitude_law_backward
    assert list(final.domain_rand.observation_delay_range) == list(shipped.domain_rand.observation_delay_range)
    assert final.rewards.scales == shipped.rewards.scales
    assert final.history_length == shipped.history_length
    assert spec.train_cfg.select_last > 0 and max(spec.train_cfg.stages) < spec.train_cfg.max_iterations
