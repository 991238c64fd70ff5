"""Evaluates trained runs on the task's fixed layouts and prints the paper's table.

Usage::

    python -m recipes.evaluate runs/point_circle/brsl/seed0 [runs/point_circle/td3/seed0 ...]
    python -m recipes.evaluate runs/point_circle/brsl/seed0 --episodes 5 --video

The deterministic policy (behind the layer for BRSL) runs one episode on each evaluation layout
(``layout=i``, ``i < task.eval_layouts``). Rows as in the paper: Table I (goal tasks) or
Table II (path tasks). Writes ``eval.csv`` / ``eval.md`` into each run, and ``reward.png``
(average episode reward over training frames of every method under ``runs/<task>/``, as the
paper's Fig. 4) next to the methods.
"""
from __future__ import annotations

import argparse
import csv
import time
from pathlib import Path

import numpy as np
import torch
from torchrl.envs.utils import ExplorationType, set_exploration_type

from recipes.environments import make_env
from recipes.runs import load_config, load_run, runs_of, seed_curves
from recipes.tasks import task_kind

#: the rows of the paper's tables: (key, label) per task kind
ROWS = {
    "goal": [("goal_rate", "Goal Rate [%]"), ("collision_rate", "Collision Rate [%]"),
             ("speed", "Mean/Max Speed [m/s]"), ("mean_reward", "Mean Reward"),
             ("compute_time", "Compute Time [ms]")],
    "path": [("collision_rate", "Collisions [% of episodes]"), ("mean_speed", "Mean Speed [m/s]"),
             ("max_speed", "Max Speed [m/s]"), ("mean_reward", "Mean Reward"),
             ("compute_time", "Compute Time [ms]")],
}


def run_episodes(cfg, actor, models, episodes: int | None = None, seed: int = 10_000, video_path=None) -> dict:
    """One deterministic episode per evaluation layout; returns the table's metrics.

    Collision rate: share of episodes with at least one contact; ``contact_steps`` adds the share
    of steps in contact (episodes of ``point_circle`` continue after a contact). Compute time:
    actor forward pass plus the layer's time, per step.
    """
    n = int(episodes or cfg.task.eval_layouts)
    rewards, goals, collided, contact_steps, speeds, times = [], [], [], [], [], []
    interventions, failsafes, holds, outside = [], [], [], []
    frames = []
    for layout in range(n):
        env = make_env(cfg, seed=seed + layout, models=models, layout=layout, evaluation=True)
        td = env.reset()
        reward, goal, hit = 0.0, False, False
        while True:
            start = time.perf_counter()
            with torch.no_grad(), set_exploration_type(ExplorationType.DETERMINISTIC):
                td = actor(td)
            policy_time = time.perf_counter() - start
            td = env.step(td)
            nxt = td["next"]
            layer = None if models is None else nxt["brsl" if cfg.method.layer else "baseline"]
            times.append(1e3 * (policy_time + (layer["compute_time"].item() if layer is not None else 0.0)))
            if layer is not None:
                interventions.append(layer["intervened"].item())
            if layer is not None and cfg.method.layer:
                failsafes.append(layer["failsafe"].item())
                holds.append(layer["unverified_hold"].item())
                outside.append(layer["out_of_data"].item())
            elif layer is not None and "fallback" in layer.keys():  # RTS: no safe trajectory, the last one goes on
                failsafes.append(layer["fallback"].item())
            reward = nxt["episode_reward"].item()  # task reward, before the layer's penalty
            speeds.append(nxt["speed"].item())
            contact_steps.append(nxt["collision"].item())
            hit |= nxt["collision"].item()
            goal |= nxt["goal_reached"].item()
            if video_path is not None and layout == 0:
                frames.append(_frame(env))
            if nxt["done"].item():
                break
            td = env.step_mdp(td)
        rewards.append(reward)
        goals.append(goal)
        collided.append(hit)
        env.close()
    if frames and all(f is not None for f in frames):
        _write_gif(frames, video_path)
    times = np.array(times)
    result = {
        "method": cfg.method.name, "task": cfg.task.name, "episodes": n,
        "goal_rate": 100 * float(np.mean(goals)),
        "collision_rate": 100 * float(np.mean(collided)),
        "contact_steps": 100 * float(np.mean(contact_steps)),
        "mean_speed": float(np.mean(speeds)), "max_speed": float(np.max(speeds)),
        "mean_reward": float(np.mean(rewards)),
        "compute_time_mean": float(times.mean()), "compute_time_std": float(times.std()),
        "intervention_rate": float(np.mean(interventions)) if interventions else float("nan"),
        "failsafe_rate": float(np.mean(failsafes)) if failsafes else float("nan"),
        "unverified_hold_rate": float(np.mean(holds)) if holds else float("nan"),
        "out_of_data_rate": float(np.mean(outside)) if outside else float("nan"),
    }
    return result


def _frame(env):
    import envs

    try:
        return env.base_env.render()
    except envs.RenderingUnavailable:
        return None


def _write_gif(frames, path) -> None:
    from PIL import Image

    images = [Image.fromarray(np.asarray(f)) for f in frames]
    images[0].save(path, save_all=True, append_images=images[1:], duration=100, loop=0)


def cell(result: dict, key: str) -> str:
    """One table cell in the paper's format (``–`` for a metric the run lacks or that does not
    apply to it, such as interventions without a safety layer)."""
    if key not in ("speed", "compute_time") and np.isnan(result.get(key, np.nan)):
        return "–"
    if key == "speed":
        return f"{result['mean_speed']:.2f} / {result['max_speed']:.2f}"
    if key == "compute_time":
        return f"{result['compute_time_mean']:.2f} ± {result['compute_time_std']:.2f}"
    if key in ("goal_rate", "collision_rate", "contact_steps"):
        return f"{result[key]:.1f}"
    return f"{result[key]:.2f}"


def table(results: list[dict], kind: str) -> str:
    """A Markdown table, methods as columns (the paper's layout)."""
    names = [r["method"] for r in results]
    title = "Table I (goal-based)" if kind == "goal" else "Table II (path following)"
    lines = [f"**{title}: {results[0]['task']}, {results[0]['episodes']} evaluation layouts**", "",
             "| | " + " | ".join(names) + " |", "|---" * (len(names) + 1) + "|"]
    extra = [("contact_steps", "Steps in contact [%]"), ("intervention_rate", "Interventions [share of steps]"),
             ("failsafe_rate", "Failsafe [share of steps]"),
             ("unverified_hold_rate", "Unverified hold [share of steps]"),
             ("out_of_data_rate", "Proposal out of data [share of steps]")]
    for key, label in ROWS[kind] + extra:
        lines.append(f"| {label} | " + " | ".join(cell(r, key) for r in results) + " |")
    return "\n".join(lines)


def write_results(results: list[dict], out_dir: Path, stem: str, kind: str) -> str:
    out_dir.mkdir(parents=True, exist_ok=True)
    with open(out_dir / f"{stem}.csv", "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=list(results[0]))
        writer.writeheader()
        writer.writerows(results)
    text = table(results, kind)
    (out_dir / f"{stem}.md").write_text(text + "\n")
    return text


def plot_rewards(task_dir: str | Path, path: str | Path | None = None) -> Path | None:
    """Episode reward over training frames per method, mean over seeds (paper Fig. 4)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    task_dir = Path(task_dir)
    runs = runs_of(task_dir)
    if not runs:
        return None
    fig, ax = plt.subplots(figsize=(5, 3.5))
    for method, dirs in sorted(runs.items()):
        curves = seed_curves(dirs, "train/episode_reward")
        if curves is None:
            continue
        grid, values = curves
        ax.plot(grid, values.mean(0), label=f"{method} ({len(values)} seed{'s' * (len(values) > 1)})")
        if len(values) > 1:
            ax.fill_between(grid, values.min(0), values.max(0), alpha=0.2)
    ax.set_xlabel("frames")
    ax.set_ylabel("episode reward")
    ax.set_title(task_dir.name)
    ax.legend()
    fig.tight_layout()
    path = Path(path or task_dir / "reward.png")
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path


def evaluate_run(run_dir: str | Path, episodes: int | None = None, video: bool = False) -> dict:
    """Evaluates one run, writes ``eval.csv``/``eval.md`` into it and returns its metrics."""
    run_dir = Path(run_dir)
    cfg, actor, models = load_run(run_dir)
    result = run_episodes(cfg, actor, models, episodes, video_path=run_dir / "episode.gif" if video else None)
    write_results([result], run_dir, "eval", task_kind(cfg.task))
    return result


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("runs", nargs="+", help="run directories (runs/<task>/<method>/seed<k>)")
    parser.add_argument("--episodes", type=int, default=None, help="layouts to evaluate (default: task.eval_layouts)")
    parser.add_argument("--video", action="store_true", help="write episode.gif of layout 0 (skipped without GL)")
    args = parser.parse_args(argv)
    by_task: dict[Path, list[dict]] = {}
    for run in args.runs:
        by_task.setdefault(Path(run).resolve().parent.parent, []).append(evaluate_run(run, args.episodes, args.video))
    for task_dir, results in by_task.items():
        print(table(results, task_kind(load_config(task_dir, results[0]["method"]).task)))
        plot = plot_rewards(task_dir)
        if plot:
            print(f"reward plot: {plot}")

if __name__ == "__main__":
    main()
