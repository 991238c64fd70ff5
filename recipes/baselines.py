"""The paper's baselines in the recipes: ``method=secas|sailr|rts`` (``method.baseline``).

Every baseline gets what BRSL gets: the task's random-input offline data (the same cached
``task.offline`` steps), the same TD3, budget and evaluation. From that data, SECAS trains its
linear constraint model (paired with obstacle layouts drawn from the task), SAILR and RTS fit
their nominal robot model (:class:`~torchrl_brsl.baselines.AffineModel`). The fitted models are
saved as ``baseline.pt`` in the run directory.
"""
from __future__ import annotations

from pathlib import Path

import torch
from omegaconf import DictConfig

from recipes.tasks import make_base_env, offline_data, task_info
from torchrl_brsl.baselines import (
    AffineModel,
    LinearSafetyModel,
    RTSSafeguard,
    SAILRIntervener,
    SECASSafetyLayer,
    TrajectoryReachableSets,
    fit_safety_model,
)

METHODS = ("secas", "sailr", "rts")
FILE = "baseline.pt"


def name(cfg: DictConfig) -> str | None:
    """``method.baseline`` (None for BRSL and TD3); a ValueError naming the option when unknown."""
    baseline = cfg.method.get("baseline")
    if baseline is None:
        return None
    if baseline not in METHODS:
        raise ValueError(f"method.baseline must be one of {METHODS}, got {baseline!r}")
    return str(baseline)


def _rts_options(cfg: DictConfig) -> DictConfig:
    options = cfg.method.tasks.get(cfg.task.name) if cfg.method.get("tasks") else None
    if options is None:
        raise ValueError(f"method=rts has no trajectory parameterisation for task {cfg.task.name!r}: add "
                         f"method.tasks.{cfg.task.name} (n_peak, n_brk, braking) to recipes/config/method/rts.yaml")
    if options.braking not in ("zero", "decelerate"):
        raise ValueError(f"method.tasks.{cfg.task.name}.braking must be 'zero' or 'decelerate', got {options.braking!r}")
    return options


def _check_signals(cfg: DictConfig, env) -> None:
    """The baselines read the robot state and the obstacle zonotopes; every task here has them."""
    spec = env.observation_spec
    missing = [key for key in ("state", ("obstacles", "center"), ("obstacles", "generators"), ("obstacles", "mask"))
               if key not in spec.keys(include_nested=True)]
    if missing:
        raise ValueError(f"method={cfg.method.name} needs the task's {missing} entries, which task "
                         f"{cfg.task.name!r} does not provide")


def fit(cfg: DictConfig, cache_dir: str | Path) -> dict:
    """The baseline's models from the task's offline data (cached like BRSL's)."""
    baseline = name(cfg)
    info = task_info(cfg.task)
    data = offline_data(cfg.task, cache_dir, cfg.seed)
    env = make_base_env(cfg.task, cfg.seed + 54321)
    _check_signals(cfg, env)
    if baseline == "rts":
        _rts_options(cfg)
    models: dict = {"nominal": AffineModel.fit(data["x_minus"], data["u_minus"], data["x_plus"])}
    if baseline == "secas":
        layouts = torch.stack([env.reset()["obstacles"] for _ in range(int(cfg.method.fit.layouts))])
        p = layouts["generators"].shape[-1]
        model = LinearSafetyModel(info.state_dim + info.obstacle_dim * (1 + p), info.action_dim, cfg.method.hidden)
        fit_safety_model(model, data, layouts, info.position_dims, pairings=cfg.method.fit.pairings,
                         steps=cfg.method.fit.steps, batch_size=cfg.method.fit.batch_size, lr=cfg.method.fit.lr,
                         margin=cfg.method.margin, seed=cfg.seed)
        models["secas"] = model
    env.close()
    return models


def save(models: dict, run_dir: str | Path) -> None:
    torch.save(models, Path(run_dir) / FILE)


def load(run_dir: str | Path) -> dict:
    return torch.load(Path(run_dir) / FILE, weights_only=False)


def make_transform(cfg: DictConfig, models: dict, evaluation: bool = False):
    """The baseline's transform, with the task's SafetyInfo (diagnostics under ``"baseline"``)."""
    baseline = name(cfg)
    info = task_info(cfg.task)
    low, high = info.action_low.double(), info.action_high.double()
    penalty = float(cfg.method.get("penalty", 0.0))
    if baseline == "secas":
        return SECASSafetyLayer(models["secas"], position_dims=info.position_dims, margin=cfg.method.margin,
                                action_low=low, action_high=high, penalty=penalty)

    def backup(state):  # the task's braking policy, in float64 and the action bounds
        return torch.maximum(torch.minimum(info.braking_policy(state.double()).double(), high.to(state.device)),
                             low.to(state.device))

    if baseline == "sailr":
        horizon = cfg.method.get("horizon") or info.n_brk + 1
        return SAILRIntervener(models["nominal"], backup, horizon=int(horizon), position_dims=info.position_dims,
                               velocity_dims=info.velocity_dims, stop_tolerance=info.stop_tolerance,
                               eta=cfg.method.eta, gamma=cfg.gamma, margin=cfg.method.margin,
                               cost_smoothing=cfg.method.cost_smoothing,
                               intervention_reward=cfg.method.intervention_reward,
                               terminate_on_intervention=not evaluation, penalty=penalty)
    options = _rts_options(cfg)
    gain = None
    if options.braking == "decelerate":  # u = -v_peak / (n_brk dt): the action dims drive the velocity dims
        gain = torch.zeros(info.action_dim, info.state_dim, dtype=torch.float64)
        for i, v in enumerate(info.velocity_dims[:info.action_dim]):
            gain[i, v] = -1.0 / (int(options.n_brk) * info.dt)
    frs = TrajectoryReachableSets(models["nominal"], n_peak=int(options.n_peak), n_brk=int(options.n_brk),
                                  position_dims=info.position_dims, action_low=low, action_high=high,
                                  cells_per_dim=cfg.method.cells_per_dim, braking_gain=gain,
                                  error_scale=cfg.method.error_scale)
    return RTSSafeguard(frs, backup, n_samples=cfg.method.n_samples, sample_std=cfg.method.sample_std,
                        seed=cfg.seed, penalty=penalty)
