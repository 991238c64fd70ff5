"""Pieces shared by the recipes: task envs, offline data and the safety layer, TD3 networks, runs.

A run directory (``runs/<task>/<method>/seed<k>/``) holds everything a run needs to be
evaluated or resumed: ``config.yaml`` (the resolved config), ``reach.pt`` (the fitted
reachability model, BRSL only; ``local_reach.pt`` for a task's low-speed model),
``checkpoint.pt``, the CSV logs under ``logs/`` and the evaluation outputs.
"""
from __future__ import annotations

import hashlib
import json
import os
import random
import warnings
from pathlib import Path
from typing import NamedTuple

warnings.filterwarnings("ignore", category=DeprecationWarning, module="torchrl")

import numpy as np  # noqa: E402
import torch  # noqa: E402
from omegaconf import DictConfig, OmegaConf  # noqa: E402
from tensordict.nn import TensorDictModule, TensorDictSequential  # noqa: E402
from torch import nn  # noqa: E402
from torchrl.envs import Compose, RewardSum, TransformedEnv  # noqa: E402
from torchrl.modules import MLP, TanhModule, ValueOperator  # noqa: E402

import envs  # noqa: E402
from torchrl_brsl.reach import (BodyFrame, DataDrivenReach, collect_offline_data, load_offline_data,  # noqa: E402
                                save_offline_data)
from torchrl_brsl.safety import BRSLSafetyLayer, Failsafe  # noqa: E402
from torchrl_brsl.sets import Zonotope  # noqa: E402

CONFIG_DIR = Path(__file__).resolve().parent / "config"

#: keys kept in the replay buffer (``action`` is the executed one)
BUFFER_KEYS = ["observation", "state", "action", ("next", "observation"), ("next", "state"), ("next", "reward"),
               ("next", "done"), ("next", "terminated")]


def seed_everything(seed: int) -> None:
    random.seed(seed)
    np.random.seed(seed)
    torch.manual_seed(seed)


def compose_config(overrides: list[str] | None = None, config_name: str = "train") -> DictConfig:
    """The training config with Hydra overrides, without running Hydra (tests, demo)."""
    from hydra import compose, initialize_config_dir

    with initialize_config_dir(config_dir=str(CONFIG_DIR), version_base=None):
        return compose(config_name=config_name, overrides=list(overrides or []))


# ----------------------------------------------------------------------------- envs
def make_base_env(task: DictConfig, seed: int, *, layout: int | None = None, empty: bool = False, **kwargs):
    """``envs.make`` with the task options of the config (``task.env``, ``task.episode_steps``)."""
    options = dict(OmegaConf.to_container(task.env, resolve=True) or {})
    if not empty and task.get("episode_steps"):
        options["episode_steps"] = int(task.episode_steps)
    options.update(kwargs)
    return envs.make(task.name, seed=seed, empty=empty, layout=layout, **options)


def make_env(cfg: DictConfig, seed: int, models: SafetyModels | dict | None = None, layout: int | None = None,
             evaluation: bool = False):
    """The training / evaluation env: the task, an episode-reward counter and, with ``models``, the
    layer (BRSL's, or a baseline's: ``models`` is then the dict of :func:`recipes.baselines.fit`).

    ``episode_reward`` sums the task's reward before the layer's penalty (the paper's metric).
    ``evaluation``: SAILR's interventions no longer end the episode.
    """
    transforms = [RewardSum(in_keys=["reward"], out_keys=["episode_reward"])]
    if models is not None:
        from recipes import baselines

        transforms.append(make_layer(cfg, models) if cfg.method.layer
                          else baselines.make_transform(cfg, models, evaluation=evaluation))
    return TransformedEnv(make_base_env(cfg.task, seed, layout=layout), Compose(*transforms))


def task_kind(task: DictConfig) -> str:
    """``"goal"`` (Table I: diffdrive_nav, quadrotor_nav) or ``"path"`` (Table II)."""
    return str(task.kind)


# ----------------------------------------------------------------------------- offline data and the layer
def regime_policy(task: DictConfig, max_speed: float):
    """Random inputs that brake (with the task's braking policy) whenever the speed exceeds ``max_speed``.

    Keeps the offline data in the operating regime: e.g. ``point_circle`` below its 2 m/s speed
    saturation, where its dynamics are linear and the data-driven sets stay tight.
    """
    info = envs.safety_info(task.name)
    low, high = info.action_low, info.action_high
    uniform = uniform_policy(low, high)

    def policy(td):
        state = td["state"]
        if state[list(info.velocity_dims)].norm() > max_speed:
            td["action"] = info.braking_policy(state.double()).float().clamp(low, high)
            return td
        return uniform(td)

    return policy


def local_domain(task: DictConfig) -> tuple[torch.Tensor, torch.Tensor]:
    """``(low, high)`` ``[n + m]`` of ``task.local`` (``null`` bounds: unbounded)."""
    info = envs.safety_info(task.name)
    bounds = []
    for side, default in (("low", -np.inf), ("high", np.inf)):
        state = task.local.get(f"state_{side}") or [default] * info.state_dim
        action = task.local.get(f"action_{side}") or [default] * info.action_dim
        bounds.append(torch.tensor([float(v) for v in [*state, *action]], dtype=torch.float64))
    return bounds[0], bounds[1]


def uniform_policy(low: torch.Tensor, high: torch.Tensor):
    """Actions drawn uniformly from ``[low, high]`` (offline data collection)."""

    def policy(td):
        td["action"] = low + (high - low) * torch.rand_like(low)
        return td

    return policy


def offline_data(task: DictConfig, cache_dir: str | Path, seed: int = 0, local: bool = False):
    """Random-input transitions in the empty task, cached on disk.

    ``task.offline.steps`` of them for the main model, or with ``local``, ``task.local.steps``
    with inputs drawn inside the local domain's action bounds. The cache key covers the task
    config, the state layout, the seed and the model kind.
    """
    options = task.local if local else task.offline
    info = envs.safety_info(task.name)
    spec = {"task": task.name, "state_dim": info.state_dim, "env": OmegaConf.to_container(task.env, resolve=True),
            "offline": OmegaConf.to_container(options, resolve=True), "seed": seed, "local": local}
    digest = hashlib.sha1(json.dumps(spec, sort_keys=True).encode()).hexdigest()[:10]
    path = Path(cache_dir) / f"{task.name}-{'local-' if local else ''}{digest}"
    if (path / "meta.json").exists():
        return load_offline_data(path)
    torch.manual_seed(seed)
    if local:
        low, high = local_domain(task)
        policy = uniform_policy(torch.maximum(info.action_low, low[info.state_dim:].float()),
                                 torch.minimum(info.action_high, high[info.state_dim:].float()))
    else:
        max_speed = task.offline.get("max_speed")
        policy = regime_policy(task, float(max_speed)) if max_speed is not None else None
    data = collect_offline_data(make_base_env(task, seed + 12345, empty=True), int(options.steps), policy=policy)
    path.parent.mkdir(parents=True, exist_ok=True)
    save_offline_data(data, path)
    return data


class SafetyModels(NamedTuple):
    """The layer's reachability models: ``reach`` (paper Alg. 2) and, when the task config has a
    ``local`` section, a second model of a low-speed domain (see :class:`BRSLSafetyLayer`)."""

    reach: DataDrivenReach
    local: DataDrivenReach | None = None

    @classmethod
    def fit(cls, cfg: DictConfig, cache_dir: str | Path) -> SafetyModels:
        """Offline data (cached) and the fitted models."""
        info = envs.safety_info(cfg.task.name)
        noise = Zonotope(info.noise_center.double(), info.noise_generators.double())
        method = cfg.method.get("reach", "local")
        if method == "auto":  # the task's choice
            method = cfg.task.safety.get("reach", "global")
        options = {"translation_invariant_dims": info.position_dims, "max_generators": cfg.method.max_generators,
                   "method": method}
        if method == "local" and info.heading_dims and cfg.method.get("body_frame", True):
            options["body_frame"] = BodyFrame(info.position_dims, info.heading_dims)
        reach = DataDrivenReach.from_data(offline_data(cfg.task, cache_dir, cfg.seed), noise, **options)
        local = None
        if cfg.task.get("local") is not None:
            local = DataDrivenReach.from_data(offline_data(cfg.task, cache_dir, cfg.seed, local=True), noise,
                                              domain=local_domain(cfg.task), **options)
        return cls(reach, local)

    def save(self, run_dir: str | Path) -> None:
        self.reach.save(Path(run_dir) / "reach.pt")
        if self.local is not None:
            self.local.save(Path(run_dir) / "local_reach.pt")

    @classmethod
    def load(cls, run_dir: str | Path) -> SafetyModels:
        local = Path(run_dir) / "local_reach.pt"
        return cls(DataDrivenReach.load(Path(run_dir) / "reach.pt"),
                   DataDrivenReach.load(local) if local.exists() else None)


def horizon(cfg: DictConfig) -> tuple[int, int]:
    """``(n_plan, n_brk)``: the task's SafetyInfo unless the task config overrides them.

    Without a planner the proposal is one action, so ``n_plan = 1``: the layer checks that
    action and the braking tail, ``1 + n_brk`` sets, rather than sets that keep growing
    after the robot has stopped.
    """
    info = envs.safety_info(cfg.task.name)
    n_plan = 1 if cfg.method.get("planner", "none") == "none" else cfg.task.safety.get("n_plan") or info.n_plan
    n_brk = cfg.task.safety.get("n_brk") or info.n_brk
    return int(n_plan), int(n_brk)


def make_layer(cfg: DictConfig, models: SafetyModels) -> BRSLSafetyLayer:
    """The safety layer with the task's SafetyInfo; stopped = final centre within the slack of rest."""
    info = envs.safety_info(cfg.task.name)
    reach = models.reach
    n_plan, n_brk = horizon(cfg)
    braking = info.braking_policy if cfg.task.safety.braking == "policy" else None
    adjuster = None if cfg.method.adjuster == "none" else cfg.method.adjuster  # the layer's registry checks the name
    return BRSLSafetyLayer(
        reach, Failsafe(info.braking_action, n_brk, policy=braking), n_plan, stop_dims=info.velocity_dims,
        stop_slack=cfg.method.stop_slack, action_low=info.action_low,
        action_high=info.action_high, adjuster=adjuster, penalty=cfg.method.penalty,
        local_reach=models.local)


# ----------------------------------------------------------------------------- TD3 networks
def make_actor(env, hidden) -> TensorDictSequential:
    """Deterministic actor ``observation -> action``, squashed into the action bounds."""
    spec = env.full_action_spec["action"]
    net = MLP(in_features=env.observation_spec["observation"].shape[-1], out_features=spec.shape[-1],
              num_cells=list(hidden), activation_class=nn.ReLU)
    return TensorDictSequential(TensorDictModule(net, in_keys=["observation"], out_keys=["param"]),
                                TanhModule(in_keys=["param"], out_keys=["action"], spec=spec))


def make_qvalue(env, hidden) -> ValueOperator:
    """Critic ``(observation, action) -> state_action_value``."""
    in_features = env.observation_spec["observation"].shape[-1] + env.full_action_spec["action"].shape[-1]
    net = MLP(in_features=in_features, out_features=1, num_cells=list(hidden), activation_class=nn.ReLU)
    return ValueOperator(net, in_keys=["observation", "action"], out_keys=["state_action_value"])


def make_planner(cfg: DictConfig, policy, env):
    """``method.planner``: ``none`` (the action is a one-step plan) or ``ensemble``.

    ``ensemble`` returns ``(planner, world_model, loss, optimiser)``: a probabilistic ensemble
    (paper Sec. IV: 4 layers of 200, leaky ReLU) trained on the replay buffer, through which
    :class:`RolloutPlanner` rolls ``policy`` for ``n_plan`` steps to write ``plan``.
    """
    if cfg.method.planner == "none":
        return None
    if cfg.method.planner != "ensemble":
        raise ValueError(f"unknown planner {cfg.method.planner!r}; choose 'none' or 'ensemble'")
    try:
        from torchrl_brsl.models import ProbabilisticEnsemble, WorldModelLoss
        from torchrl_brsl.planning import RolloutPlanner
    except ImportError as error:
        raise NotImplementedError("method.planner=ensemble needs torchrl_brsl.models and torchrl_brsl.planning, "
                                  "which this installation does not provide; use method.planner=none") from error
    ens = cfg.method.ensemble
    model = ProbabilisticEnsemble(env.observation_spec["observation"].shape[-1],
                                  env.full_action_spec["action"].shape[-1], ensemble_size=ens.size,
                                  hidden_size=ens.hidden_size, num_layers=ens.num_layers)
    planner = RolloutPlanner(policy, model, n_plan=horizon(cfg)[0])
    return planner, model, WorldModelLoss(model), torch.optim.Adam(model.parameters(), lr=ens.lr)


# ----------------------------------------------------------------------------- runs on disk
def load_run(run_dir: str | Path):
    """``(cfg, actor, models)`` of a trained run (``models`` is None for methods without a layer)."""
    run_dir = Path(run_dir)
    cfg = OmegaConf.load(run_dir / "config.yaml")
    from recipes import baselines

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


def threads(n: int) -> None:
    """Small MLPs run several times faster on one thread than on two."""
    torch.set_num_threads(int(n))
    os.environ.setdefault("OMP_NUM_THREADS", str(n))
