"""TD3 on a task, behind the BRSL safety layer (``method=brsl``), unprotected (``method=td3``) or
behind one of the paper's baselines (``method=secas|sailr|rts``, see :mod:`recipes.baselines`).

Usage::

    python -m recipes.train task=point_circle method=brsl seed=0 total_frames=20000

Paper Algorithm 1: the actor (+ decaying Gaussian exploration) proposes an action, the layer
executes a verified-safe one and penalises unsafe proposals, the replay buffer stores the
*executed* action with the penalised reward, and TD3 trains on minibatches. Everything lands
in ``runs/<task>/<method>/seed<k>/``; a second call with the same arguments resumes.
"""
from __future__ import annotations

import shutil
import time
from dataclasses import dataclass
from pathlib import Path

import hydra
import torch
import tqdm
from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig, OmegaConf
from tensordict.nn import TensorDictModuleBase, TensorDictSequential
from torchrl.collectors import Collector
from torchrl.data import LazyTensorStorage, ReplayBuffer
from torchrl.objectives import SoftUpdate, TD3Loss
from torchrl.record.loggers import get_logger

from recipes import baselines
from recipes.environments import EnvFactory, make_env
from recipes.evaluate import evaluate_run
from recipes.networks import Planner, make_actor, make_exploration, make_planner, make_qvalue
from recipes.safety_models import SafetyModels
from recipes.setup import seed_everything, threads

#: keys kept in the replay buffer (``action`` is the executed one)
BUFFER_KEYS = ["observation", "state", "action", ("next", "observation"), ("next", "state"), ("next", "reward"),
               ("next", "done"), ("next", "terminated")]


def train(cfg: DictConfig, run_dir: str | Path) -> dict:
    """Trains (or resumes) one run; returns the last logged metrics and totals."""
    run_dir = Path(run_dir)
    baseline = baselines.name(cfg)  # None for brsl and td3
    learn_executed = _learns_from_executed(cfg, baseline)
    ckpt = _open_run(cfg, run_dir)  # None for a fresh run
    frames = ckpt["frames"] if ckpt else 0
    seed_everything(cfg.seed + frames)

    # --- the layer's models (BRSL's or a baseline's), fitted once on random-input steps in the empty task
    models = _safety_models(cfg, run_dir, baseline, resume=ckpt is not None)

    # --- env, TD3 (actor, critics, exploration, planner), replay buffer
    env = make_env(cfg, cfg.seed + frames, models)
    agent = Agent.make(cfg, env)
    buffer = ReplayBuffer(storage=LazyTensorStorage(cfg.buffer_size), batch_size=cfg.batch_size)
    totals = {"frames": frames, "updates": 0, "episodes": 0, "collisions": 0, "interventions": 0, "failsafes": 0}
    if ckpt is not None:
        agent.load_state_dict(ckpt)
        totals.update(ckpt["totals"])
        if (run_dir / "buffer").exists():
            buffer.loads(run_dir / "buffer")
    if cfg.total_frames <= frames:
        env.close()
        return {"totals": totals, "metrics": {}}

    # --- collect, store, update (paper Algorithm 1), log, checkpoint
    collector = _make_collector(cfg, env, agent.policy, models, frames)
    logger = _make_logger(cfg, run_dir)
    bar = tqdm.tqdm(total=cfg.total_frames, initial=frames, disable=not cfg.progress, desc=str(run_dir))
    next_checkpoint = (frames // cfg.checkpoint.every_frames + 1) * cfg.checkpoint.every_frames
    metrics: dict = {}
    start = time.perf_counter()
    for data in collector:
        data = data.reshape(-1)
        n = data.numel()
        if learn_executed:  # the executed action; its reward is already penalised by the layer
            data["action"] = data["next", "safe_action"]
        buffer.extend(data.select(*BUFFER_KEYS))
        agent.exploration.step(n)
        totals["frames"] += n
        losses = agent.update(cfg, buffer, n, totals)
        collector.update_policy_weights_()
        fps = (totals["frames"] - frames) / (time.perf_counter() - start)
        metrics = _batch_metrics(cfg, baseline, data, totals, agent.exploration.sigma.item(), fps, losses)
        _log(logger, bar, metrics, totals["frames"], n)
        if totals["frames"] >= next_checkpoint:
            _save_checkpoint(cfg, run_dir, agent, totals, buffer)
            next_checkpoint += cfg.checkpoint.every_frames

    # --- the final checkpoint, and the evaluation
    bar.close()
    collector.shutdown()
    _save_checkpoint(cfg, run_dir, agent, totals, buffer)
    if cfg.eval_after:
        evaluate_run(run_dir)
    return {"totals": totals, "metrics": metrics}


def _learns_from_executed(cfg: DictConfig, baseline: str | None) -> bool:
    """Whether the buffer stores the executed action (``method.learn_from=executed``) rather than the proposal
    (``proposed``: the layer is then part of the agent's environment); only a layer or a baseline changes it."""
    if not (cfg.method.layer or baseline is not None):
        return False
    if cfg.method.learn_from not in ("executed", "proposed"):
        raise ValueError(f"method.learn_from must be 'executed' or 'proposed', got {cfg.method.learn_from!r}")
    return cfg.method.learn_from == "executed"


def _open_run(cfg: DictConfig, run_dir: Path) -> dict | None:
    """Writes ``config.yaml`` and sets the threads; returns the checkpoint to resume from, or None for a fresh
    run, whose earlier logs and buffer are removed (not appended to)."""
    run_dir.mkdir(parents=True, exist_ok=True)
    OmegaConf.save(cfg, run_dir / "config.yaml", resolve=True)
    threads(cfg.threads)
    if cfg.resume and (run_dir / "checkpoint.pt").exists():
        return torch.load(run_dir / "checkpoint.pt", weights_only=False)
    shutil.rmtree(run_dir / "logs", ignore_errors=True)
    shutil.rmtree(run_dir / "buffer", ignore_errors=True)
    return None


def _safety_models(cfg: DictConfig, run_dir: Path, baseline: str | None, resume: bool):
    """BRSL's :class:`SafetyModels`, a baseline's models, or None (TD3): loaded from the run when resuming,
    otherwise fitted on the task's offline data and saved into the run."""
    if cfg.method.layer:
        if resume and (run_dir / "reach.pt").exists():
            return SafetyModels.load(run_dir)
        models = SafetyModels.fit(cfg, cfg.cache_dir)
        models.save(run_dir)
        return models
    if baseline is None:
        return None
    models = baselines.load(run_dir) if resume and (run_dir / baselines.FILE).exists() \
        else baselines.fit(cfg, cfg.cache_dir)
    baselines.save(models, run_dir)
    return models


@dataclass
class Agent:
    """TD3 with two critics, delayed actor and target updates; ``policy`` (the collector's) is the actor with
    exploration noise, rolled through the world model with ``method.planner=ensemble``."""

    actor: TensorDictSequential
    exploration: TensorDictModuleBase
    policy: TensorDictModuleBase
    planner: Planner | None
    loss: TD3Loss
    target_update: SoftUpdate
    critic_opt: torch.optim.Optimizer
    actor_opt: torch.optim.Optimizer

    @classmethod
    def make(cls, cfg: DictConfig, env) -> Agent:
        actor, qvalue = make_actor(env, cfg.hidden), make_qvalue(env, cfg.hidden)
        exploration = make_exploration(cfg.exploration, env)
        policy = TensorDictSequential(actor, exploration)
        planner = make_planner(cfg, policy, env)
        loss = TD3Loss(actor, qvalue, action_spec=env.full_action_spec["action"], num_qvalue_nets=2,
                       policy_noise=cfg.policy_noise, noise_clip=cfg.noise_clip, loss_function="l2")
        loss.make_value_estimator(gamma=cfg.gamma)
        return cls(actor, exploration, policy if planner is None else planner.rollout, planner, loss,
                   SoftUpdate(loss, tau=cfg.tau),
                   torch.optim.Adam(loss.qvalue_network_params.flatten_keys().values(), lr=cfg.lr_critic),
                   torch.optim.Adam(loss.actor_network_params.flatten_keys().values(), lr=cfg.lr_actor))

    def update(self, cfg: DictConfig, buffer: ReplayBuffer, n: int, totals: dict) -> dict:
        """After ``n`` new frames: TD3 updates (from ``init_random_frames`` on), then the world model on the same
        buffer; returns the mean losses and counts the updates into ``totals``."""
        q_losses, a_losses = [], []
        if totals["frames"] >= cfg.init_random_frames:
            for _ in range(max(1, int(n * cfg.updates_per_frame))):
                batch = buffer.sample()
                q_losses.append(_step(self.loss.value_loss(batch)[0], self.critic_opt))
                totals["updates"] += 1
                if totals["updates"] % cfg.policy_delay == 0:
                    a_losses.append(_step(self.loss.actor_loss(batch)[0], self.actor_opt))
                    self.target_update.step()
        losses = {}
        if self.planner is not None:
            losses["train/loss_world_model"] = self.planner.update(buffer, cfg.method.ensemble)
        if q_losses:
            losses["train/loss_qvalue"] = sum(q_losses) / len(q_losses)
        if a_losses:
            losses["train/loss_actor"] = sum(a_losses) / len(a_losses)
        return losses

    def state_dict(self) -> dict:
        state = {"actor": self.actor.state_dict(), "loss": self.loss.state_dict(),
                 "critic_opt": self.critic_opt.state_dict(), "actor_opt": self.actor_opt.state_dict(),
                 "exploration": self.exploration.state_dict()}
        if self.planner is not None:
            state.update(world_model=self.planner.world_model.state_dict(),
                         world_model_opt=self.planner.optimiser.state_dict())
        return state

    def load_state_dict(self, state: dict) -> None:
        """From a checkpoint (the actor's weights are part of the loss's)."""
        self.loss.load_state_dict(state["loss"])
        self.critic_opt.load_state_dict(state["critic_opt"])
        self.actor_opt.load_state_dict(state["actor_opt"])
        self.exploration.load_state_dict(state["exploration"])
        if self.planner is not None:
            self.planner.world_model.load_state_dict(state["world_model"])
            self.planner.optimiser.load_state_dict(state["world_model_opt"])


def _step(loss: torch.Tensor, optimiser: torch.optim.Optimizer) -> float:
    optimiser.zero_grad()
    loss.backward()
    optimiser.step()
    return loss.item()


def _make_collector(cfg: DictConfig, env, policy, models, frames: int) -> Collector:
    """The remaining frames: one local process by default; ``num_collectors`` / ``collector_backend`` to scale
    out (each collector process then builds its own env, with its own seed)."""
    remote = cfg.num_collectors > 1 or bool(cfg.collector_backend)
    no_registration = {"auto_register_policy_transforms": False}  # the layer belongs to the env, not the policy
    kwargs = dict(no_registration)
    if remote:
        env.close()
        env = EnvFactory(cfg, cfg.seed + frames, models)
        kwargs = {"num_collectors": cfg.num_collectors, "backend": cfg.collector_backend}
        if cfg.collector_backend == "ray":  # passed on to the remote collectors; weights synced between
            # batches (Ray's weight sync cannot reach an actor that is busy collecting)
            kwargs.update(collector_kwargs=no_registration, sync=True)
        else:
            kwargs.update(no_registration)
    collector = Collector(env, policy, frames_per_batch=cfg.frames_per_batch, total_frames=cfg.total_frames - frames,
                          init_random_frames=max(0, cfg.init_random_frames - frames), **kwargs)
    if remote:  # distinct seeds per collector process (the single local env is seeded already)
        collector.set_seed(cfg.seed + frames)
        collector.update_policy_weights_()
    return collector


def _make_logger(cfg: DictConfig, run_dir: Path):
    """``logger.backend`` (csv, tensorboard, wandb) writing under ``<run>/logs``; None when empty."""
    if not cfg.logger.backend:
        return None
    return get_logger(cfg.logger.backend, logger_name=str(run_dir / "logs"), experiment_name="train",
                      **({"project": cfg.logger.project} if cfg.logger.backend == "wandb" else {}))


def _batch_metrics(cfg: DictConfig, baseline: str | None, data, totals: dict, sigma: float, fps: float,
                   losses: dict) -> dict:
    """Counts a batch ``[N]`` into ``totals`` and returns its metrics: the task's, the losses and the layer's."""
    done = data["next", "done"].squeeze(-1)
    collisions = int(data["next", "collision"].sum())
    totals["episodes"] += int(done.sum())
    totals["collisions"] += collisions
    metrics = {"train/collisions": collisions, "train/collisions_total": totals["collisions"],
               "train/speed": data["next", "speed"].mean().item(), "train/sigma": sigma,
               "train/frames_per_second": fps}
    if done.any():
        metrics["train/episode_reward"] = data["next", "episode_reward"][done].mean().item()
    metrics.update(losses)
    if cfg.method.layer:
        brsl = data["next", "brsl"]
        totals["interventions"] += int(brsl["intervened"].sum())
        totals["failsafes"] += int(brsl["failsafe"].sum())
        metrics.update({"brsl/intervention_rate": brsl["intervened"].float().mean().item(),
                        "brsl/failsafe_rate": brsl["failsafe"].float().mean().item(),
                        "brsl/unverified_hold_rate": brsl["unverified_hold"].float().mean().item(),
                        "brsl/out_of_data_rate": brsl["out_of_data"].float().mean().item(),
                        "brsl/compute_time_ms": 1e3 * brsl["compute_time"].mean().item(),
                        "brsl/min_collision_value": brsl["min_collision_value"].min().item()})
    if baseline is not None:
        diag = data["next", "baseline"]
        totals["interventions"] += int(diag["intervened"].sum())
        metrics.update({f"{baseline}/intervention_rate": diag["intervened"].float().mean().item(),
                        f"{baseline}/compute_time_ms": 1e3 * diag["compute_time"].mean().item()})
    return metrics


def _log(logger, bar: tqdm.tqdm, metrics: dict, frames: int, n: int) -> None:
    if logger is not None:
        for name, value in metrics.items():
            logger.log_scalar(name, value, step=frames)
    bar.update(n)
    bar.set_postfix({k.split("/")[1][:12]: round(v, 3) for k, v in metrics.items()
                     if k in ("train/episode_reward", "train/collisions_total", "brsl/intervention_rate")})


def _save_checkpoint(cfg: DictConfig, run_dir: Path, agent: Agent, totals: dict, buffer: ReplayBuffer) -> None:
    torch.save({**agent.state_dict(), "frames": totals["frames"], "totals": dict(totals)}, run_dir / "checkpoint.pt")
    if cfg.checkpoint.save_buffer:
        buffer.dumps(run_dir / "buffer")


@hydra.main(config_path="config", config_name="train", version_base=None)
def main(cfg: DictConfig) -> None:
    result = train(cfg, HydraConfig.get().runtime.output_dir)
    print({k: v for k, v in result["totals"].items()})


if __name__ == "__main__":
    main()
