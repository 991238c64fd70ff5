"""Finished runs on disk: a run's config, actor and models, the runs of a task, and their logged scalars.

A run directory (``runs/<task>/<method>/seed<k>/``) holds everything a run needs to be
evaluated or resumed: ``config.yaml`` (the resolved config), ``reach.pt`` (the fitted
reachability model, BRSL only; ``local_reach.pt`` for a task's low-speed model),
``checkpoint.pt``, the CSV logs under ``logs/`` and the evaluation outputs. :func:`archive_run` copies
the few kilobytes the tables and Fig. 4 read (config, evaluation, training totals, reward curve) into
another root, e.g. ``docs/runs``, where runs from different machines add up.
"""
from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import torch
from omegaconf import DictConfig, OmegaConf

from recipes import baselines
from recipes.environments import make_env
from recipes.networks import make_actor
from recipes.safety_models import SafetyModels
from recipes.setup import threads


def load_run(run_dir: str | Path):
    """``(cfg, actor, models)`` of a trained run (``models`` is None for methods without a layer)."""
    run_dir = Path(run_dir)
    cfg = OmegaConf.load(run_dir / "config.yaml")
    threads(cfg.threads)  # before the layer: its compiled steps are specialised to the thread count
    models = SafetyModels.load(run_dir) if cfg.method.layer else baselines.load(run_dir) \
        if baselines.name(cfg) else None
    env = make_env(cfg, seed=0, models=models)
    actor = make_actor(env, cfg.hidden)
    state = torch.load(run_dir / "checkpoint.pt", map_location="cpu", weights_only=False)
    actor.load_state_dict(state["actor"])
    env.close()
    return cfg, actor, models


def load_config(task_dir: str | Path, method: str) -> DictConfig:
    """The config of the first run of ``method`` under ``task_dir``."""
    return OmegaConf.load(runs_of(task_dir)[method][0] / "config.yaml")


def runs_of(task_dir: str | Path) -> dict[str, list[Path]]:
    """``{method: [run dirs]}`` under ``<root>/<task>/<method>/seed<k>``."""
    found: dict[str, list[Path]] = {}
    for config in sorted(Path(task_dir).glob("*/seed*/config.yaml")):
        found.setdefault(config.parent.parent.name, []).append(config.parent)
    return found


#: the logged scalars an archived run keeps (Fig. 4 reads the episode reward)
ARCHIVED_SCALARS = ("train/episode_reward",)


def finished(run_dir: str | Path) -> bool:
    """Whether ``run_dir`` is a finished run: trained here (a checkpoint) or archived (an evaluation)."""
    return (Path(run_dir) / "checkpoint.pt").exists() or (Path(run_dir) / "totals.json").exists()


def training_totals(run_dir: str | Path) -> dict:
    """The training counters of a run (frames, episodes, collisions, interventions, ...): its
    checkpoint's, or an archived run's ``totals.json``; empty when neither exists."""
    run_dir = Path(run_dir)
    if (run_dir / "totals.json").exists():
        return json.loads((run_dir / "totals.json").read_text())
    if (run_dir / "checkpoint.pt").exists():
        return dict(torch.load(run_dir / "checkpoint.pt", map_location="cpu", weights_only=False)["totals"])
    return {}


def archive_run(run_dir: str | Path, dest: str | Path) -> Path:
    """Copies what the tables and Fig. 4 read from an evaluated run into ``dest``: ``config.yaml``,
    ``eval.csv`` / ``eval.md``, the training totals as ``totals.json`` and the logged
    :data:`ARCHIVED_SCALARS` (a few kilobytes in all; no weights, no buffer). Returns ``dest``.

    Example::

        archive_run("runs/table20/point_circle/td3/seed0", "docs/runs/table20/point_circle/td3/seed0")
    """
    run_dir, dest = Path(run_dir), Path(dest)
    missing = [n for n in ("config.yaml", "checkpoint.pt", "eval.csv") if not (run_dir / n).exists()]
    if missing:
        raise FileNotFoundError(f"{run_dir} is not an evaluated run: {', '.join(missing)} missing "
                                f"(train it, then `python -m recipes.evaluate {run_dir}`)")
    dest.mkdir(parents=True, exist_ok=True)
    for name in ("config.yaml", "eval.csv", "eval.md"):
        if (run_dir / name).exists():
            shutil.copy2(run_dir / name, dest / name)
    (dest / "totals.json").write_text(json.dumps(training_totals(run_dir), indent=1) + "\n")
    for name in ARCHIVED_SCALARS:
        for src in run_dir.glob(f"logs/*/scalars/{name}.csv"):
            target = dest / src.relative_to(run_dir)
            target.parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(src, target)
    return dest


def read_scalar(run_dir: str | Path, name: str) -> tuple[np.ndarray, np.ndarray]:
    """``(steps, values)`` of one scalar from a run's CSV log (TorchRL ``CSVLogger`` layout)."""
    files = list(Path(run_dir, "logs").glob(f"*/scalars/{name}.csv"))
    if not files:
        return np.zeros(0), np.zeros(0)
    rows = np.loadtxt(files[0], delimiter=",", ndmin=2)
    return (rows[:, 0], rows[:, 1]) if rows.size else (np.zeros(0), np.zeros(0))


def seed_curves(run_dirs, name: str) -> tuple[np.ndarray, np.ndarray] | None:
    """One scalar of several runs on a common step grid: ``(grid [S], values [runs, S])``, or
    ``None`` when no run logged it (runs without it are left out)."""
    curves = [c for c in (read_scalar(d, name) for d in run_dirs) if len(c[0])]
    if not curves:
        return None
    grid = np.unique(np.concatenate([steps for steps, _ in curves]))
    return grid, np.stack([np.interp(grid, steps, values) for steps, values in curves])
