"""Smoke runs of the recipes on tiny budgets, and the safety of BRSL training (MuJoCo contacts)."""
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from recipes import safety_models
from recipes.compare import compare
from recipes.evaluate import evaluate_run, main as evaluate_main
from recipes.runs import load_run, read_scalar
import envs
from recipes.safety_models import COMPILE_FROM_FRAMES, compiles_reach, horizon, layer_settings
from recipes.setup import compose_config
from recipes.tasks import make_base_env
from recipes.train import train
from torchrl_brsl.reach import BodyFrame

TINY = ["frames_per_batch=100", "init_random_frames=200", "batch_size=64", "hidden=[32,32]",
        "checkpoint.every_frames=200", "progress=false", "task.eval_layouts=2"]


def config(tmp, task, method, frames, *extra):
    return compose_config([f"task={task}", f"method={method}", f"root={tmp}", f"total_frames={frames}",
                                  *TINY, *extra])


def run_dir(tmp, task, method, seed=0):
    return Path(tmp) / task / method / f"seed{seed}"


@pytest.fixture(scope="module")
def point_boxes_runs(tmp_path_factory):
    """BRSL and TD3 trained for 600 frames on point_boxes (linear variant), BRSL then resumed to 800."""
    tmp = tmp_path_factory.mktemp("runs")
    torch.set_num_threads(1)
    brsl = train(config(tmp, "point_boxes", "brsl", 600), run_dir(tmp, "point_boxes", "brsl"))
    resumed = train(config(tmp, "point_boxes", "brsl", 800), run_dir(tmp, "point_boxes", "brsl"))
    td3 = train(config(tmp, "point_boxes", "td3", 600), run_dir(tmp, "point_boxes", "td3"))
    return tmp, brsl, resumed, td3


def test_brsl_training_never_collides(point_boxes_runs):
    _, brsl, resumed, td3 = point_boxes_runs
    assert brsl["totals"]["frames"] == 600
    assert brsl["totals"]["collisions"] == 0 and resumed["totals"]["collisions"] == 0
    # the layer was active, and the same exploration without it collides: the check is meaningful
    assert brsl["totals"]["interventions"] > 0
    assert td3["totals"]["collisions"] > 0


def test_runs_write_config_reach_checkpoint_and_logs(point_boxes_runs):
    tmp = point_boxes_runs[0]
    brsl, td3 = run_dir(tmp, "point_boxes", "brsl"), run_dir(tmp, "point_boxes", "td3")
    for path in ("config.yaml", "reach.pt", "checkpoint.pt"):
        assert (brsl / path).exists()
    assert not (td3 / "reach.pt").exists()
    steps, rewards = read_scalar(brsl, "train/episode_reward")
    assert len(steps) > 0 and torch.isfinite(torch.as_tensor(rewards)).all()
    for name in ("brsl/intervention_rate", "brsl/failsafe_rate", "brsl/compute_time_ms", "train/loss_qvalue",
                 "train/loss_actor", "train/collisions"):
        assert len(read_scalar(brsl, name)[0]) > 0, name
    assert len(read_scalar(td3, "brsl/intervention_rate")[0]) == 0


def test_resume_continues_from_the_checkpoint(point_boxes_runs):
    tmp, brsl, resumed, _ = point_boxes_runs
    assert resumed["totals"]["frames"] == 800
    assert resumed["totals"]["updates"] > brsl["totals"]["updates"]
    state = torch.load(run_dir(tmp, "point_boxes", "brsl") / "checkpoint.pt", weights_only=False)
    assert state["frames"] == 800
    steps, _ = read_scalar(run_dir(tmp, "point_boxes", "brsl"), "train/collisions")
    assert steps.max() == 800 and len(set(steps.tolist())) == len(steps)  # logs continued, not restarted
    # a finished run returns at once
    again = train(config(tmp, "point_boxes", "brsl", 800), run_dir(tmp, "point_boxes", "brsl"))
    assert again["totals"]["frames"] == 800


def test_evaluate_and_compare(point_boxes_runs, capsys):
    tmp = point_boxes_runs[0]
    result = evaluate_run(run_dir(tmp, "point_boxes", "brsl"))
    assert result["episodes"] == 2 and result["collision_rate"] == 0.0
    assert 0.0 <= result["unverified_hold_rate"] <= result["failsafe_rate"]
    assert (run_dir(tmp, "point_boxes", "brsl") / "eval.md").exists()
    evaluate_main([str(run_dir(tmp, "point_boxes", "td3")), "--episodes", "1"])
    out = capsys.readouterr().out
    assert "Table II" in out and "Compute Time [ms]" in out
    text = compare(Path(tmp) / "point_boxes", reuse=True)
    assert "| brsl | td3 |" in text.splitlines()[2].replace("  ", " ")
    for name in ("comparison.csv", "comparison.md", "reward.png"):
        assert (Path(tmp) / "point_boxes" / name).exists()


def test_point_circle_layer_accepts_plans(tmp_path):
    """With offline data below the speed saturation and n_brk = 12 the sets are small enough to move."""
    out = train(config(tmp_path, "point_circle", "brsl", 200, "init_random_frames=200"),
                run_dir(tmp_path, "point_circle", "brsl"))
    assert out["metrics"]["brsl/failsafe_rate"] < 0.5
    assert out["metrics"]["train/speed"] > 0.05


def test_goal_task_table(tmp_path):
    train(config(tmp_path, "diffdrive_nav", "td3", 100, "init_random_frames=100", "task.episode_steps=30"),
          run_dir(tmp_path, "diffdrive_nav", "td3"))
    result = evaluate_run(run_dir(tmp_path, "diffdrive_nav", "td3"), episodes=1)
    assert 0.0 <= result["goal_rate"] <= 100.0
    text = compare(tmp_path / "diffdrive_nav", reuse=True)
    assert "Table I" in text
    interventions = next(line for line in text.splitlines() if line.startswith("| Interventions"))
    assert interventions.split("|")[2].strip() == "–"  # no safety layer: not applicable, not NaN


def test_ensemble_planner(tmp_path):
    pytest.importorskip("torchrl_brsl.planning")
    out = train(config(tmp_path, "point_boxes", "brsl", 300, "method.planner=ensemble", "method.ensemble.size=2",
                       "method.ensemble.hidden_size=32", "method.ensemble.updates_per_batch=2"),
                run_dir(tmp_path, "point_boxes", "brsl"))
    assert out["totals"]["collisions"] == 0
    assert len(read_scalar(run_dir(tmp_path, "point_boxes", "brsl"), "train/loss_world_model")[0]) > 0


def test_unknown_planner_is_rejected(tmp_path):
    cfg = config(tmp_path, "point_boxes", "brsl", 100, "method.planner=mpc")
    with pytest.raises(ValueError, match="planner"):
        train(cfg, run_dir(tmp_path, "point_boxes", "brsl"))


def test_unknown_adjuster_is_rejected_by_name(tmp_path):
    cfg = config(tmp_path, "point_boxes", "brsl", 100, "method.adjuster=newton")
    with pytest.raises(ValueError, match="adjuster.*newton"):
        train(cfg, run_dir(tmp_path, "point_boxes", "brsl"))


def test_learn_from_proposals_runs_and_bad_values_are_rejected(tmp_path):
    cfg = config(tmp_path, "point_boxes", "brsl", 200, "method.learn_from=proposed")
    assert train(cfg, run_dir(tmp_path, "point_boxes", "brsl"))["totals"]["frames"] == 200
    with pytest.raises(ValueError, match="learn_from"):
        train(config(tmp_path, "point_boxes", "brsl", 200, "method.learn_from=both"),
              run_dir(tmp_path, "point_boxes", "brsl2"))


def test_hydra_entry_point(tmp_path):
    cmd = [sys.executable, "-m", "recipes.train", "task=point_boxes", "method=td3", f"root={tmp_path}",
           "total_frames=100", "init_random_frames=100", *TINY[:1], *TINY[2:5]]
    subprocess.run(cmd, check=True, capture_output=True, cwd=Path(__file__).resolve().parents[2])
    assert (run_dir(tmp_path, "point_boxes", "td3") / "checkpoint.pt").exists()


@pytest.mark.parametrize("schedule", ["geometric", "linear"])
def test_exploration_is_damped_every_frame(tmp_path, schedule):
    train(config(tmp_path, "point_boxes", "td3", 400, f"exploration.schedule={schedule}", "exploration.sigma_end=0.1"),
          run_dir(tmp_path, "point_boxes", "td3"))
    _, sigma = read_scalar(run_dir(tmp_path, "point_boxes", "td3"), "train/sigma")
    assert (sigma[1:] < sigma[:-1]).all() and sigma[-1] == pytest.approx(0.1, rel=1e-4)
    if schedule == "geometric":  # a constant ratio per batch of frames
        assert sigma[2] / sigma[1] == pytest.approx(sigma[1] / sigma[0], rel=1e-4)
    with pytest.raises(ValueError, match="schedule"):
        train(config(tmp_path, "point_boxes", "td3", 100, "exploration.schedule=cosine"),
              run_dir(tmp_path, "point_boxes", "other"))


def test_without_a_planner_the_layer_checks_one_action_and_the_braking_tail():
    assert horizon(compose_config(["task=diffdrive_nav"])) == (1, 6)
    assert horizon(compose_config(["task=diffdrive_nav", "method.planner=ensemble"])) == (8, 6)
    assert horizon(compose_config(["task=point_circle", "method.planner=ensemble"])) == (5, 12)


def test_the_reach_steps_are_compiled_for_long_runs_only_by_default():
    assert compiles_reach(compose_config(["task=diffdrive_nav", f"total_frames={COMPILE_FROM_FRAMES}"]))
    assert not compiles_reach(compose_config(["task=diffdrive_nav", "total_frames=1000"]))
    assert not compiles_reach(compose_config(["task=diffdrive_nav", "total_frames=20000",
                                              "method.compile_reach=false"]))
    assert compiles_reach(compose_config(["task=diffdrive_nav", "total_frames=100", "method.compile_reach=true"]))
    with pytest.raises(ValueError, match="method.compile_reach"):
        compiles_reach(compose_config(["task=diffdrive_nav", "method.compile_reach=sometimes"]))



@pytest.mark.parametrize("found, advice", [({"tcmalloc": "/lib/libtcmalloc_minimal.so.4"},
                                            "LD_PRELOAD=/lib/libtcmalloc_minimal.so.4"),
                                           ({}, "apt install libtcmalloc-minimal4")])
def test_a_compiled_layer_on_the_system_malloc_is_told_how_to_preload_a_caching_one(monkeypatch, found, advice):
    monkeypatch.setattr(safety_models, "installed_allocators", lambda: found)
    assert advice in safety_models.allocator_hint()


#: the overrides of the task's SafetyInfo that the default task configs document: (n_plan, n_brk)
CONFIG_OVERRIDES = {"point_circle": (5, 12)}


@pytest.mark.parametrize("planner", ["none", "ensemble"])
@pytest.mark.parametrize("task", envs.TASKS)
def test_the_layer_settings_of_the_default_configs_are_the_task_safety_info(task, planner):
    settings = layer_settings(compose_config([f"task={task}", f"method.planner={planner}"]))
    info = envs.safety_info(task)
    n_plan, n_brk = CONFIG_OVERRIDES.get(task, (info.n_plan, info.n_brk))
    assert (settings.n_plan, settings.n_brk) == (1 if planner == "none" else n_plan, n_brk)
    assert settings.stop_dims == info.velocity_dims
    for key in ("braking_action", "action_low", "action_high"):
        assert torch.equal(getattr(settings, key), getattr(info, key)), key
    assert settings.braking_policy == (info.braking_policy if task == "point_circle" else None)


@pytest.mark.parametrize("task", envs.TASKS)
def test_the_default_configs_keep_the_task_episode_length(task):
    env = make_base_env(compose_config([f"task={task}"]).task, seed=0)
    assert env._env._step_limit == pytest.approx(envs._registry._task(task).episode_steps - 0.5)


def test_collector_processes(tmp_path):
    out = train(config(tmp_path, "point_boxes", "brsl", 400, "num_collectors=2", "collector_backend=process"),
                run_dir(tmp_path, "point_boxes", "brsl"))
    assert out["totals"]["frames"] == 400 and out["totals"]["collisions"] == 0


def test_ray_collectors(tmp_path):
    pytest.importorskip("ray", reason="the Ray backend needs `pip install .[ray]`")
    out = train(config(tmp_path, "point_boxes", "brsl", 400, "num_collectors=2", "collector_backend=ray"),
                run_dir(tmp_path, "point_boxes", "brsl"))
    assert out["totals"]["frames"] == 400 and out["totals"]["collisions"] == 0


def test_demo_trains_both_methods_and_prints_the_table(tmp_path, capsys):
    from recipes.demo import main as demo_main

    demo_main(["--task", "point_boxes", "--frames", "400", "--root", str(tmp_path)])
    out = capsys.readouterr().out
    assert "brsl: 400 frames" in out and "td3: 400 frames" in out and "| brsl | td3 |" in out.replace("  ", " ")
    assert (tmp_path / "point_boxes" / "reward.png").exists()


def test_diffdrive_brsl_run_saves_and_reloads_its_models(tmp_path):
    """The task's choice (``method.reach=auto``): the local model in the body frame, and the low-speed model (each
    fitted from 500 offline steps instead of the recipe's 2,000: the choice and the round trip do not depend on it)."""
    train(config(tmp_path, "diffdrive_nav", "brsl", 100, "init_random_frames=100", "task.episode_steps=30",
                 "task.offline.steps=500", "task.local.steps=500"), run_dir(tmp_path, "diffdrive_nav", "brsl"))
    assert (run_dir(tmp_path, "diffdrive_nav", "brsl") / "local_reach.pt").exists()
    _, _, models = load_run(run_dir(tmp_path, "diffdrive_nav", "brsl"))
    assert models.local is not None and models.local.bounded_domain and not models.reach.bounded_domain
    assert models.reach.method == "local" and models.reach.body_frame == BodyFrame((0, 1), (2, 3))
    assert evaluate_run(run_dir(tmp_path, "diffdrive_nav", "brsl"), episodes=1)["collision_rate"] == 0.0
