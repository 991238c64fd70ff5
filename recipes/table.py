"""The paper's Tables I and II and Fig. 4 over every run under a root, mean ± std over seeds.

Usage::

    python -m recipes.table runs [--reuse] [--episodes N] [--out docs/tables.md]
    python -m recipes.table runs/table20 --reuse --archive docs/runs/table20   # keep them, tabulate all kept

Reads ``<root>/<task>/<method>/seed<k>`` for every task and method, evaluates each run (or
reuses its ``eval.csv`` with ``--reuse``, leaving out with a warning the runs that have none
yet) and prints, as in the paper, Table I (goal tasks:
Turtlebot = ``diffdrive_nav``, quadrotor = ``quadrotor_nav``) and Table II (path tasks: point =
``point_circle``, ``hexarotor_wind``; other path tasks follow), tasks side by side and the
methods BRSL, RTS, SAILR, SECAS, Baseline (TD3) as columns, then the ablations. BRSL is the
paper's: the ensemble world model rolls the policy out into the plan the layer checks (runs
trained with ``method.name=brsl_ensemble method.planner=ensemble``); the recipe's default (one
action, then braking: ``method=brsl``) is the ablation "BRSL (one action, then braking)", and
``learn_from: executed`` (``method.name=brsl_executed``) another; ``brsl_rotor`` and ``td3_rotor`` are the
recipe's default and TD3 on the rotor-driven multirotors (``+task.env.robot=rotor``). Every cell is the mean ± std over
seeds (the seed count is a row), compute time the per-step mean ± per-step std averaged over
seeds; a method without runs on a task shows ``–``. Extra rows: collision steps during training
(summed over the run, mean ± std over seeds) and interventions. Writes ``fig4.png`` (episode
reward over training frames, mean and a ±std band over seeds, one panel per task) into the root.

``--archive DEST`` first copies every evaluated run under the root into ``DEST`` (its config,
evaluation, training totals and reward curve: :func:`recipes.runs.archive_run`), then tabulates
``DEST``, which holds these runs and any archived before, from other machines too. An archived
run is read from its ``eval.csv`` (it has no weights to evaluate again).
"""
from __future__ import annotations

import argparse
import csv
import warnings
from pathlib import Path

import numpy as np

from recipes.runs import archive_run, finished, load_config, runs_of, seed_curves, training_totals
from recipes.tasks import task_kind

#: the paper's column order (its BRSL: the ensemble world model rolling the policy out into the plan,
#: ``method.name=brsl_ensemble method.planner=ensemble``); its names for the columns, and the ablations'
METHODS = ["brsl_ensemble", "rts", "sailr", "secas", "td3"]
LABELS = {"brsl_ensemble": "BRSL", "rts": "RTS", "sailr": "SAILR", "secas": "SECAS", "td3": "Baseline",
          "brsl": "BRSL (one action, then braking)", "brsl_executed": "BRSL (learns executed)",
          "brsl_rotor": "BRSL (one action, then braking), rotor robot", "td3_rotor": "Baseline, rotor robot"}
#: the paper's tasks per table (others of the same kind follow), with its names for them
TASKS = {"goal": ["diffdrive_nav", "quadrotor_nav"], "path": ["point_circle", "hexarotor_wind"]}
TASK_LABELS = {"diffdrive_nav": "Turtlebot", "quadrotor_nav": "Quadrotor", "point_circle": "Point",
               "hexarotor_wind": "Hexarotor"}
ROWS = {
    "goal": [("goal_rate", "Goal Rate [%]", "{:.0f}"), ("collision_rate", "Collision Rate [%]", "{:.1f}"),
             ("speed", "Mean/Max Speed [m/s]", None), ("mean_reward", "Mean Reward", "{:.0f}"),
             ("compute_time", "Compute Time [ms]", None)],
    "path": [("collision_rate", "Collisions [%]", "{:.1f}"), ("mean_speed", "Mean Speed [m/s]", "{:.2f}"),
             ("max_speed", "Max Speed [m/s]", "{:.2f}"), ("mean_reward", "Mean Reward", "{:.0f}"),
             ("compute_time", "Compute Time [ms]", None)],
}
EXTRA = [("train_collision_steps", "Collision steps in training", "{:.0f}"),
         ("intervention_rate", "Interventions [share of steps]", "{:.2f}"),
         ("failsafe_rate", "Failsafe [share of steps]", "{:.2f}"),
         ("unverified_hold_rate", "Unverified hold [share of steps]", "{:.2f}"), ("seeds", "Seeds", "{:.0f}")]


def _read_eval(run_dir: Path) -> dict:
    with open(run_dir / "eval.csv") as f:
        row = next(csv.DictReader(f))
    return {k: (v if k in ("method", "task") else float(v)) for k, v in row.items()}


def training_collisions(run_dir: Path) -> float:
    """Steps in contact during training (the run's totals; nan when it has none)."""
    return float(training_totals(run_dir).get("collisions", float("nan")))


def collect(root: str | Path, episodes: int | None = None, reuse: bool = False) -> dict:
    """``{task: {"kind": kind, "methods": {method: [per-seed metrics]}}}`` of every run under ``root``."""
    from recipes.evaluate import evaluate_run

    out: dict = {}
    for task_dir in sorted(p for p in Path(root).iterdir() if p.is_dir()):
        runs = runs_of(task_dir)
        if not runs:
            continue
        kind = task_kind(load_config(task_dir, next(iter(runs))).task)
        methods = {}
        for method, dirs in runs.items():
            rows = []
            for d in dirs:
                if not finished(d):
                    continue  # a run still starting
                archived = not (d / "checkpoint.pt").exists()  # only its evaluation is kept
                if reuse and not (d / "eval.csv").exists():
                    warnings.warn(f"{d}: no evaluation to reuse (still training?); left out of the tables")
                    continue
                row = _read_eval(d) if (reuse or archived) else evaluate_run(d, episodes)
                row["train_collision_steps"] = training_collisions(d)
                rows.append(row)
            if rows:
                methods[method] = rows
        out[task_dir.name] = {"kind": kind, "methods": methods}
    return out


def archive_runs(root: str | Path, dest: str | Path) -> int:
    """Archives every evaluated run ``<root>/<task>/<method>/seed<k>`` into the same place under
    ``dest`` (replacing an earlier copy); returns how many."""
    kept = 0
    for task_dir in (p for p in Path(root).iterdir() if p.is_dir()):
        for dirs in runs_of(task_dir).values():
            for d in (d for d in dirs if (d / "eval.csv").exists() and (d / "checkpoint.pt").exists()):
                archive_run(d, Path(dest) / d.relative_to(root))
                kept += 1
    return kept


def _format(fmt: str, value: float) -> str:
    text = fmt.format(value)
    return text.lstrip("-") if float(text) == 0 else text  # no "-0"


def _mean_std(values, fmt: str) -> str:
    values = np.asarray([v for v in values if not np.isnan(v)], dtype=float)
    if values.size == 0:
        return "–"
    if values.size == 1:
        return _format(fmt, values[0])
    return f"{_format(fmt, values.mean())} ± {_format(fmt, values.std())}"


def cell(rows: list[dict] | None, key: str, fmt: str | None) -> str:
    """One cell: mean ± std over the seeds' values (``–`` without runs or where it does not apply)."""
    if not rows:
        return "–"
    if key == "seeds":
        return str(len(rows))
    if key == "speed":
        return f"{_mean_std([r['mean_speed'] for r in rows], '{:.2f}')} / {_mean_std([r['max_speed'] for r in rows], '{:.2f}')}"
    if key == "compute_time":
        mean = np.mean([r["compute_time_mean"] for r in rows])
        std = np.mean([r["compute_time_std"] for r in rows])
        return f"{mean:.2f} ± {std:.2f}"
    return _mean_std([r.get(key, np.nan) for r in rows], fmt)


def columns(results: dict, tasks: list[str]) -> list[str]:
    """The paper's methods, then any other run directory of these ``tasks`` (an ablation such as ``brsl``, the
    recipe's default: one action, then braking)."""
    found = {m for t in tasks for m in results[t]["methods"]}
    return METHODS + sorted(found - set(METHODS))


def tables(results: dict) -> str:
    """Table I and Table II in Markdown, the paper's layout (tasks side by side); ablations (runs under
    another method directory, e.g. ``brsl``, the recipe's default) follow the paper's columns."""
    text = []
    for kind, title in (("goal", "Table I: goal-based experiments"), ("path", "Table II: path following")):
        tasks = [t for t in TASKS[kind] if t in results] + sorted(
            t for t, r in results.items() if r["kind"] == kind and t not in TASKS[kind])
        if not tasks:
            continue
        methods = columns(results, tasks)
        header = "| |" + "|".join(f" {TASK_LABELS.get(t, t)}: {LABELS.get(m, m)} " for t in tasks for m in methods)
        rule = "|---" * (1 + len(tasks) * len(methods)) + "|"
        lines = [f"**{title}** (mean ± std over seeds)", "", header + "|", rule]
        for key, label, fmt in ROWS[kind] + EXTRA:
            cells = [cell(results[t]["methods"].get(m), key, fmt) for t in tasks for m in methods]
            lines.append(f"| {label} | " + " | ".join(cells) + " |")
        text.append("\n".join(lines))
    return "\n\n".join(text)


def plot_fig4(root: str | Path, results: dict, path: str | Path | None = None) -> Path | None:
    """Episode reward over training frames, mean and ±std band over seeds, one panel per task."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    tasks = [t for kind in ("goal", "path") for t in TASKS[kind] if t in results]
    tasks += sorted(t for t in results if t not in tasks)
    if not tasks:
        return None
    fig, axes = plt.subplots(1, len(tasks), figsize=(4.5 * len(tasks), 3.5), squeeze=False)
    for ax, task in zip(axes[0], tasks):
        runs = runs_of(Path(root) / task)
        for method in [m for m in METHODS if m in runs] + sorted(m for m in runs if m not in METHODS):
            curves = seed_curves(runs[method], "train/episode_reward")
            if curves is None:
                continue
            grid, values = curves
            ax.plot(grid, values.mean(0), label=f"{LABELS.get(method, method)} ({len(values)})")
            if len(values) > 1:
                ax.fill_between(grid, values.mean(0) - values.std(0), values.mean(0) + values.std(0), alpha=0.2)
        ax.set_title(TASK_LABELS.get(task, task))
        ax.set_xlabel("frames")
        ax.set_ylabel("episode reward")
        ax.legend(fontsize=7)
    fig.tight_layout()
    path = Path(path or Path(root) / "fig4.png")
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("root", help="the runs root (<root>/<task>/<method>/seed<k>)")
    parser.add_argument("--episodes", type=int, default=None, help="layouts per run (default: task.eval_layouts)")
    parser.add_argument("--reuse", action="store_true", help="reuse each run's eval.csv when present")
    parser.add_argument("--out", default=None, help="also write the tables to this Markdown file")
    parser.add_argument("--archive", default=None, help="copy the evaluated runs into this root, tabulate it")
    args = parser.parse_args(argv)
    root = args.root
    if args.archive:
        kept = archive_runs(root, args.archive)
        print(f"archived {kept} evaluated runs of {root} into {args.archive}")
        root = args.archive
    results = collect(root, args.episodes, args.reuse)
    if not any(r["methods"] for r in results.values()):
        raise SystemExit(f"no finished runs under {root} (expected <task>/<method>/seed<k>/checkpoint.pt)")
    text = tables(results)
    print(text)
    if args.out:
        Path(args.out).write_text(text + "\n")
    figure = plot_fig4(root, results)
    if figure:
        print(f"\nFig. 4: {figure}")


if __name__ == "__main__":
    main()
