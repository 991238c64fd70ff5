"""BRSL and TD3 (and any other method trained on the task) side by side in one table.

Usage::

    python -m recipes.compare runs/point_circle [--episodes N] [--reuse]

Evaluates every ``runs/<task>/<method>/seed<k>`` (or reuses its ``eval.csv`` with ``--reuse``),
averages the metrics over seeds, prints the paper's table with one column per method and
writes ``comparison.csv``, ``comparison.md`` and ``reward.png`` into ``runs/<task>/``.
"""
from __future__ import annotations

import argparse
import csv
from pathlib import Path

import numpy as np

from recipes.evaluate import evaluate_run, plot_rewards, write_results
from recipes.runs import load_config, runs_of
from recipes.tasks import task_kind

#: methods in the paper's column order; others follow alphabetically
ORDER = ["brsl", "td3"]


def _read_eval(run_dir: Path) -> dict:
    with open(run_dir / "eval.csv") as f:
        row = next(csv.DictReader(f))
    return {k: (v if k in ("method", "task") else float(v)) for k, v in row.items()}


def compare(task_dir: str | Path, episodes: int | None = None, reuse: bool = False) -> str:
    """Evaluates (or reuses) every run under ``task_dir``; returns the Markdown table."""
    task_dir = Path(task_dir)
    runs = runs_of(task_dir)
    if not runs:
        raise FileNotFoundError(f"no runs under {task_dir} (expected <method>/seed<k>/config.yaml)")
    columns = []
    for method in sorted(runs, key=lambda m: (ORDER.index(m) if m in ORDER else len(ORDER), m)):
        per_seed = [_read_eval(d) if reuse and (d / "eval.csv").exists() else evaluate_run(d, episodes)
                    for d in runs[method]]
        merged = {k: (v if isinstance(v, str) else float(np.mean([r.get(k, np.nan) for r in per_seed])))
                  for k, v in per_seed[0].items()}
        merged["max_speed"] = max(r["max_speed"] for r in per_seed)
        merged["seeds"] = len(per_seed)
        merged["method"] = f"{method}" + (f" ({len(per_seed)} seeds)" if len(per_seed) > 1 else "")
        merged["episodes"] = int(merged["episodes"])
        columns.append(merged)
    kind = task_kind(load_config(task_dir, next(iter(runs))).task)
    text = write_results(columns, task_dir, "comparison", kind)
    plot_rewards(task_dir)
    return text


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("task_dir", help="runs/<task>")
    parser.add_argument("--episodes", type=int, default=None, help="layouts per run (default: task.eval_layouts)")
    parser.add_argument("--reuse", action="store_true", help="reuse each run's eval.csv when present")
    args = parser.parse_args(argv)
    print(compare(args.task_dir, args.episodes, args.reuse))
    print(f"written: {Path(args.task_dir) / 'comparison.md'}, {Path(args.task_dir) / 'reward.png'}")


if __name__ == "__main__":
    main()
