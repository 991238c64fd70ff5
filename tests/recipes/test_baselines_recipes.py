"""The baselines in the recipes: ``method=secas|sailr|rts`` train, resume, evaluate, and bad configs are named."""
from pathlib import Path

import pytest
import torch
from hydra.errors import MissingConfigException

from recipes import baselines
from recipes.environments import make_env
from recipes.evaluate import evaluate_run
from recipes.runs import read_scalar
from recipes.setup import compose_config
from recipes.train import train

TINY = ["frames_per_batch=100", "init_random_frames=200", "batch_size=64", "hidden=[32,32]",
        "checkpoint.every_frames=200", "progress=false", "task.eval_layouts=2"]


def config(tmp, task, method, frames, *extra):
    return compose_config([f"task={task}", f"method={method}", f"root={tmp}", f"total_frames={frames}",
                                  *TINY, *extra])


@pytest.mark.parametrize("method", baselines.METHODS)
def test_each_baseline_trains_resumes_and_evaluates(tmp_path, method):
    torch.set_num_threads(1)
    run = Path(tmp_path) / "point_boxes" / method / "seed0"
    out = train(config(tmp_path, "point_boxes", method, 300, "method.fit.steps=200" if method == "secas" else "seed=0"),
                run)
    assert out["totals"]["frames"] == 300 and (run / baselines.FILE).exists()
    assert f"{method}/intervention_rate" in out["metrics"] and f"{method}/compute_time_ms" in out["metrics"]
    assert len(read_scalar(run, f"{method}/intervention_rate")[0]) > 0
    resumed = train(config(tmp_path, "point_boxes", method, 400, "method.fit.steps=200" if method == "secas"
                           else "seed=0"), run)
    assert resumed["totals"]["frames"] == 400 and resumed["totals"]["updates"] > out["totals"]["updates"]
    result = evaluate_run(run)
    assert result["method"] == method and result["episodes"] == 2
    assert 0.0 <= result["intervention_rate"] <= 1.0 and result["compute_time_mean"] > 0
    if method == "rts":
        assert 0.0 <= result["failsafe_rate"] <= result["intervention_rate"]


def test_sailr_interventions_end_training_episodes_with_the_absorbing_reward(tmp_path):
    cfg = config(tmp_path, "point_circle", "sailr", 300, "init_random_frames=300")
    models = baselines.fit(cfg, tmp_path / "cache")
    env = make_env(cfg, 0, models)
    td = env.rollout(300, lambda td: td.set("action", torch.where(td["state"][:2] >= 0, 1.0, -1.0).float()))
    assert td["next", "baseline", "intervened"][-1].item() and td["next", "terminated"][-1].item()
    assert td["next", "reward"][-1].item() == cfg.method.intervention_reward
    assert not td["next", "collision"].any()
    # in evaluation the backup acts and the episode goes on
    env = make_env(cfg, 0, models, evaluation=True)
    td = env.rollout(60, lambda td: td.set("action", torch.where(td["state"][:2] >= 0, 1.0, -1.0).float()))
    assert td.shape[0] == 60 and td["next", "baseline", "intervened"].sum() > 1 and not td["next", "collision"].any()


def test_bad_configurations_name_the_option(tmp_path):
    with pytest.raises(MissingConfigException, match="method"):
        config(tmp_path, "point_boxes", "cbf", 100)
    with pytest.raises(ValueError, match="method.baseline"):
        train(config(tmp_path, "point_boxes", "secas", 100, "method.baseline=cbf"), tmp_path / "a")
    with pytest.raises(ValueError, match="method.tasks.point_boxes"):
        train(config(tmp_path, "point_boxes", "rts", 100, "~method.tasks.point_boxes"), tmp_path / "b")
    with pytest.raises(ValueError, match="braking"):
        train(config(tmp_path, "point_boxes", "rts", 100, "method.tasks.point_boxes.braking=spiral"), tmp_path / "c")
    with pytest.raises(ValueError, match="learn_from"):
        train(config(tmp_path, "point_boxes", "sailr", 100, "method.learn_from=both"), tmp_path / "d")


def test_table_cells_are_mean_and_std_over_seeds():
    from recipes.table import cell

    rows = [{"mean_reward": 10.0, "mean_speed": 0.5, "max_speed": 2.0, "compute_time_mean": 1.0,
             "compute_time_std": 0.2}, {"mean_reward": 20.0, "mean_speed": 0.7, "max_speed": 1.0,
                                        "compute_time_mean": 3.0, "compute_time_std": 0.4}]
    assert cell(rows, "mean_reward", "{:.0f}") == "15 ± 5"
    assert cell(rows, "speed", None) == "0.60 ± 0.10 / 1.50 ± 0.50"
    assert cell(rows, "compute_time", None) == "2.00 ± 0.30"
    assert cell(rows[:1], "mean_reward", "{:.0f}") == "10" and cell(rows, "seeds", None) == "2"
    assert cell(None, "mean_reward", "{:.0f}") == "–" and cell(rows, "goal_rate", "{:.0f}") == "–"
    assert cell([{"mean_reward": -0.3}], "mean_reward", "{:.0f}") == "0"


def test_table_prints_both_tables_in_the_paper_layout(tmp_path, capsys):
    from recipes.table import main as table_main

    for task, method, seed in (("point_boxes", "td3", 0), ("point_boxes", "td3", 1), ("point_boxes", "sailr", 0),
                               ("diffdrive_nav", "td3", 0)):
        extra = ["task.episode_steps=30", "init_random_frames=100"] if task == "diffdrive_nav" else []
        train(config(tmp_path, task, method, 200, f"seed={seed}", "task.eval_layouts=1", *extra),
              Path(tmp_path) / task / method / f"seed{seed}")
    table_main([str(tmp_path), "--out", str(tmp_path / "tables.md")])
    out = capsys.readouterr().out
    assert "Table I" in out and "Table II" in out and (tmp_path / "fig4.png").exists()
    goal, path = out.split("**Table II")

    def rows(text):
        return {line.split("|")[1].strip(): [c.strip() for c in line.split("|")[2:-1]]
                for line in text.splitlines() if line.startswith("| ")}

    assert rows(goal)[""] == ["Turtlebot: BRSL", "Turtlebot: RTS", "Turtlebot: SAILR", "Turtlebot: SECAS",
                              "Turtlebot: Baseline"]
    assert rows(goal)["Seeds"] == ["–", "–", "–", "–", "1"]
    assert rows(path)[""][2] == "point_boxes: SAILR"
    assert rows(path)["Seeds"] == ["–", "–", "1", "–", "2"]
    assert "±" in rows(path)["Mean Reward"][4]  # two seeds of td3: mean ± std
    assert (tmp_path / "tables.md").read_text().strip() in out

    # archived: the same tables from a few kilobytes per run, no weights, on any machine
    archive = tmp_path.parent / f"{tmp_path.name}_archive"
    table_main([str(tmp_path), "--reuse", "--archive", str(archive), "--out", str(archive / "tables.md")])
    assert (archive / "tables.md").read_text() == (tmp_path / "tables.md").read_text()
    assert not list(archive.rglob("*.pt")) and (archive / "fig4.png").exists()
    kept = [f for f in archive.rglob("*") if f.is_file() and f.suffix != ".png"]
    assert sum(f.stat().st_size for f in kept) < 4 * 16_000
    assert "archived 4 evaluated runs" in capsys.readouterr().out
    (tmp_path / "point_boxes" / "td3" / "seed1" / "eval.csv").unlink()  # as while it still trains
    with pytest.warns(UserWarning, match="seed1: no evaluation to reuse"):
        table_main([str(tmp_path), "--reuse", "--out", str(tmp_path / "partial.md")])
    assert "±" not in (tmp_path / "partial.md").read_text().split("**Table II")[1].split("Mean Reward")[1].split("\n")[0]


def test_table_puts_ablation_runs_after_the_papers_columns_with_the_failsafe_shares():
    from recipes.table import tables

    row = {"goal_rate": 50.0, "collision_rate": 0.0, "mean_speed": 0.1, "max_speed": 0.2, "mean_reward": 5.0,
           "compute_time_mean": 1.0, "compute_time_std": 0.1, "intervention_rate": 0.3, "failsafe_rate": 0.05,
           "unverified_hold_rate": 0.01, "train_collision_steps": 0.0}
    methods = {"brsl": [row], "brsl_ensemble": [dict(row, goal_rate=70.0)]}
    results = {"diffdrive_nav": {"kind": "goal", "methods": methods},
               "point_circle": {"kind": "path", "methods": {"brsl_executed": [row]}}}  # its table only
    goal, path = tables(results).split("**Table II")
    lines = {line.split("|")[1].strip(): [c.strip() for c in line.split("|")[2:-1]]
             for line in goal.splitlines() if line.startswith("| ")}
    assert "BRSL (learns executed)" in path and "executed" not in goal
    assert lines[""][0] == "Turtlebot: BRSL" and len(lines[""]) == 6  # the paper's BRSL: the ensemble planner
    assert lines[""][5] == "Turtlebot: BRSL (one action, then braking)"
    assert lines["Goal Rate [%]"] == ["70", "–", "–", "–", "–", "50"]
    assert lines["Failsafe [share of steps]"][0] == "0.05" and lines["Unverified hold [share of steps]"][0] == "0.01"
