"""The baselines in the recipes: ``method=secas|sailr|rts`` train, resume, evaluate, and bad configs are named."""
from pathlib import Path

import pytest
import torch
from hydra.errors import MissingConfigException

from recipes import baselines, common
from recipes.evaluate import evaluate_run
from recipes.train import train

TINY = ["frames_per_batch=100", "init_random_frames=200", "batch_size=64", "hidden=[32,32]",
        "checkpoint.every_frames=200", "progress=false", "task.eval_layouts=2"]


def config(tmp, task, method, frames, *extra):
    return common.compose_config([f"task={task}", f"method={method}", f"root={tmp}", f"total_frames={frames}",
                                  *TINY, *extra])


@pytest.mark.parametrize("method", baselines.METHODS)
def test_each_baseline_trains_resumes_and_evaluates(tmp_path, method):
    torch.set_num_threads(1)
    run = Path(tmp_path) / "point_boxes" / method / "seed0"
    out = train(config(tmp_path, "point_boxes", method, 300, "method.fit.steps=200" if method == "secas" else "seed=0"),
                run)
    assert out["totals"]["frames"] == 300 and (run / baselines.FILE).exists()
    assert f"{method}/intervention_rate" in out["metrics"] and f"{method}/compute_time_ms" in out["metrics"]
    assert len(common.read_scalar(run, f"{method}/intervention_rate")[0]) > 0
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
    env = common.make_env(cfg, 0, models)
    td = env.rollout(300, lambda td: td.set("action", torch.where(td["state"][:2] >= 0, 1.0, -1.0).float()))
    assert td["next", "baseline", "intervened"][-1].item() and td["next", "terminated"][-1].item()
    assert td["next", "reward"][-1].item() == cfg.method.intervention_reward
    assert not td["next", "collision"].any()
    # in evaluation the backup acts and the episode goes on
    env = common.make_env(cfg, 0, models, evaluation=True)
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
