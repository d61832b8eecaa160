"""scripts/reproduce.py --quick: every experiment runs and lands on the page with its figure."""

from __future__ import annotations

import numpy as np
import pytest

from legged_casters.tools import reproduce


def test_quick_reproduction_writes_every_experiment(tmp_path, capsys):
    assert reproduce.main(["--quick", "--out", str(tmp_path)]) == 0
    page = (tmp_path / "results.md").read_text()
    for experiment in (
        "Fig. 3",
        "Fig. 6",
        "Fig. 9",
        "Fig. 10",
        "Table II",
        "Fig. 1 / Fig. 8 slalom",
        "Table II course",
    ):
        assert f"| {experiment}" in page, experiment
    rows = [line for line in page.splitlines() if line.startswith("| Fig. 6 error angles")]
    seconds = float(rows[0].split("|")[3].split()[0])
    assert 0.0 < seconds < 5.0  # the posture recovers after the reversal (measured, not typed)
    for name in (
        "fig3_force.png",
        "fig6_posture.png",
        "fig9_top_speed.png",
        "fig10_modes.png",
        "fig8_slalom.png",
        "fig11_course.png",
    ):
        assert (tmp_path / "results" / name).stat().st_size > 5000
        assert f"(results/{name})" in page
    assert reproduce.main(["--only", "fig99", "--out", str(tmp_path)]) == 2
    assert "unknown" in capsys.readouterr().err


def test_course_terrain_follows_its_profile():
    from legged_casters import registry
    from legged_casters.robot import terrain

    start, segments, end = reproduce.course_segments(quick=True)
    env = registry.make_env(
        "go2_wheel_flat", {"terrain.segments": [list(s) for s in segments], "terrain.start_x": start}, num_envs=1
    )
    top = terrain.profile(segments, start)[1]
    assert top[1] == top[3] > 0.2  # the flat top is raised by the climb
    import mujoco

    data = mujoco.MjData(env.model)
    mujoco.mj_forward(env.model, data)
    for x in (start + 1.0, (top[0] + top[2]) / 2, end - 0.5):  # a ray straight down meets the course surface
        geom = np.zeros(1, dtype=np.int32)
        dist = mujoco.mj_ray(env.model, data, np.array([x, 0.0, 5.0]), np.array([0.0, 0.0, -1.0]), None, 1, -1, geom)
        assert 5.0 - dist == pytest.approx(terrain.Course(segments, start).height(x), abs=1e-6)
    env.close()


def test_robots_spawn_on_the_course_at_the_right_height_and_evaluation_is_flat():
    import torch

    from legged_casters import registry
    from legged_casters.robot import terrain
    from legged_casters.tools import evaluate

    segments = [[6.0, 5.0], [2.0, 0.0], [6.0, -5.0]]
    cfg = {"terrain.segments": segments, "terrain.start_x": 1.0, "terrain.width": 10.0, "terrain.spawn_on_course": True}
    env = registry.make_env("go2_wheel_flat", cfg, num_envs=32, seed=3)
    ground = terrain.Course(segments, 1.0).height_torch(env.base_pos[:, 0])
    assert (ground > 0.1).any() and (env.base_pos[:, 0] > 0.5).all()  # spread over the course, hill included
    for _ in range(25):
        env.step(torch.zeros(32, env.num_actions))
    assert torch.allclose(env.base_height, torch.full_like(env.base_height, 0.38), atol=0.05)  # standing on it
    env.close()
    spec = registry.get_task("go2_wheel_flat")
    flat = evaluate.eval_env_cfg(reproduce.common.with_overrides(spec.env_cfg, cfg, "t"), evaluate.QUICK[:1])
    assert flat.terrain.segments == []


def test_a_trace_keeps_every_step_and_starts_at_the_origin(monkeypatch):
    """Each recorded step is its own copy (the sim reuses its state buffers: Fig. 7's frames
    were once all the last step), and a run starts standing at the origin even for a
    policy whose training config spawned robots along a course."""
    load = reproduce.evaluate.load_exported

    def trained_on_a_course(*args, **kwargs):
        out = load(*args, **kwargs)
        out[2].terrain.spawn_on_course = True  # the env config, as a course-trained export carries it
        return out

    monkeypatch.setattr(reproduce.evaluate, "load_exported", trained_on_a_course)
    tr = reproduce.run_policy(
        "caster_omni",
        1.0,
        lambda t, env: (0.5, 0.0, 0.0),
        overrides={"terrain.segments": [[10.0, 3.0]], "terrain.start_x": 2.0},
    )
    qpos = tr.extra["qpos"]
    assert len(qpos) == len(tr.t) and not np.allclose(qpos[0], qpos[-1])
    np.testing.assert_allclose(qpos[:, 0], tr.pos[:, 0], atol=1e-5)
    assert abs(tr.pos[0, 0]) < 0.05 and abs(tr.pos[0, 1]) < 0.05


def test_path_follower_says_stalled_only_without_progress():
    import torch

    path = np.c_[np.arange(0.0, 100.0, 0.25), np.zeros(400)]
    f = reproduce.PathFollower(path, 1.0)
    env = type("Env", (), {})()
    env.base_quat = torch.tensor([[1.0, 0.0, 0.0, 0.0]])
    for k in range(100):  # 0.5 m/s for 100 s: slow, never stalled
        env.base_pos = torch.tensor([[0.5 * k, 0.0, 0.4]])
        f(float(k), env)
        assert not f.stalled()
    for k in range(100, 170):  # then stuck at 49.5 m
        f(float(k), env)
    assert f.stalled() and not f.done


def test_trained_on_reads_the_task_a_shipped_policy_names():
    """A shipped folder whose policy.yaml names another task than the folder (caster_omni:
    caster_omni_sym) is described from its own configs, not refused as a task mismatch."""
    assert reproduce.trained_on("caster_omni") == "trained on flat ground"
