"""BRSL's safety layer: the reachability models fitted on the task's offline data, the horizon it checks,
and the layer itself."""
from __future__ import annotations

import functools
from pathlib import Path
from typing import Callable, NamedTuple

from omegaconf import DictConfig
from torch import Tensor

from recipes.tasks import local_domain, offline_data, task_info
from torchrl_brsl._malloc import installed_allocators, malloc_name
from torchrl_brsl.reach import BodyFrame, DataDrivenReach
from torchrl_brsl.safety import BRSLSafetyLayer, Failsafe
from torchrl_brsl.sets import Zonotope


class SafetyModels(NamedTuple):
    """The layer's reachability models: ``reach`` (paper Alg. 2) and, when the task config has a
    ``local`` section, a second model of a low-speed domain (see :class:`BRSLSafetyLayer`)."""

    reach: DataDrivenReach
    local: DataDrivenReach | None = None

    @classmethod
    def fit(cls, cfg: DictConfig, cache_dir: str | Path) -> SafetyModels:
        """Offline data (cached) and the fitted models."""
        info = task_info(cfg.task)
        noise = Zonotope(info.noise_center.double(), info.noise_generators.double())
        method = cfg.method.get("reach", "local")
        if method == "auto":  # the task's choice
            method = cfg.task.safety.get("reach", "global")
        options = {"translation_invariant_dims": info.position_dims, "max_generators": cfg.method.max_generators,
                   "method": method, "progress": bool(cfg.get("progress", False))}
        body_frame = method == "local" and info.heading_dims and cfg.method.get("body_frame", True)
        options["body_frame"] = BodyFrame(info.position_dims, info.heading_dims) if body_frame else None
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


class LayerSettings(NamedTuple):
    """What the layer takes from the task: its SafetyInfo, with the plan and braking lengths resolved."""

    n_plan: int
    n_brk: int
    braking_action: Tensor
    braking_policy: Callable[[Tensor], Tensor] | None
    stop_dims: tuple[int, ...]
    action_low: Tensor
    action_high: Tensor


def layer_settings(cfg: DictConfig) -> LayerSettings:
    """The task's SafetyInfo, where the task config's ``safety`` section overrides ``n_plan`` and ``n_brk``
    (``null``: the task's), with the braking policy when ``safety.braking`` is ``policy``.

    Without a planner the proposal is one action, so ``n_plan = 1``: the layer checks that
    action and the braking tail, ``1 + n_brk`` sets, rather than sets that keep growing
    after the robot has stopped.
    """
    info = task_info(cfg.task)
    safety = cfg.task.safety

    def resolved(key: str) -> int:
        return int(getattr(info, key) if safety.get(key) is None else safety.get(key))

    return LayerSettings(
        n_plan=1 if cfg.method.get("planner", "none") == "none" else resolved("n_plan"), n_brk=resolved("n_brk"),
        braking_action=info.braking_action, braking_policy=info.braking_policy if safety.braking == "policy" else None,
        stop_dims=info.velocity_dims, action_low=info.action_low, action_high=info.action_high)


def horizon(cfg: DictConfig) -> tuple[int, int]:
    """``(n_plan, n_brk)`` of :func:`layer_settings`."""
    settings = layer_settings(cfg)
    return settings.n_plan, settings.n_brk


def make_layer(cfg: DictConfig, models: SafetyModels) -> BRSLSafetyLayer:
    """The safety layer with the task's :func:`layer_settings`; stopped = final centre within the slack of rest."""
    settings = layer_settings(cfg)
    if compiles_reach(cfg):  # a local model's steps; a global one's braking-policy tail (PlanChecker)
        for model in models:
            if model is not None:
                model.compile_steps()
        _say_allocator_hint()
    adjuster = None if cfg.method.adjuster == "none" else cfg.method.adjuster  # the layer's registry checks the name
    return BRSLSafetyLayer(
        models.reach, Failsafe(settings.braking_action, settings.n_brk, policy=settings.braking_policy),
        settings.n_plan, stop_dims=settings.stop_dims, stop_slack=cfg.method.stop_slack,
        action_low=settings.action_low, action_high=settings.action_high, adjuster=adjuster,
        penalty=cfg.method.penalty, local_reach=models.local)


def allocator_hint() -> str:
    """How to run the compiled layer faster: with a caching malloc preloaded (``docs/install.md``)."""
    found = installed_allocators()
    how = (f"run with LD_PRELOAD={next(iter(found.values()))}" if found
           else "install one (Debian: apt install libtcmalloc-minimal4) and preload it")
    return f"note: the compiled layer runs 1.2-1.4x faster with a caching malloc; {how} (docs/install.md)"


@functools.cache
def _say_allocator_hint() -> None:
    """Print :func:`allocator_hint` once per process, on the system malloc."""
    if malloc_name() == "system malloc":
        print(allocator_hint())


COMPILE_FROM_FRAMES = 5_000


def compiles_reach(cfg: DictConfig) -> bool:
    """``method.compile_reach``: ``true``, ``false`` or ``auto`` (runs of ``COMPILE_FROM_FRAMES`` frames or more,
    where the minute or two of compilation pays back; :meth:`DataDrivenReach.compile_steps`)."""
    choice = cfg.method.get("compile_reach", "auto")
    if choice == "auto":
        return int(cfg.total_frames) >= COMPILE_FROM_FRAMES
    if not isinstance(choice, bool):
        raise ValueError(f"`method.compile_reach` must be true, false or auto, got {choice!r}")
    return choice
