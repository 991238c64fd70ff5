"""TD3 on a task, behind the BRSL safety layer (``method=brsl``), unprotected (``method=td3``) or
behind one of the paper's baselines (``method=secas|sailr|rts``, see :mod:`recipes.baselines`).

    python -m recipes.train task=point_circle method=brsl seed=0 total_frames=20000

Paper Algorithm 1: the actor (+ decaying Gaussian exploration) proposes an action, the layer
executes a verified-safe one and penalises unsafe proposals, the replay buffer stores the
*executed* action with the penalised reward, and TD3 trains on minibatches. Everything lands
in ``runs/<task>/<method>/seed<k>/``; a second call with the same arguments resumes.
"""
from __future__ import annotations

import shutil
import time
import warnings
from pathlib import Path

import hydra
import torch
import tqdm
from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig, OmegaConf
from tensordict.nn import TensorDictSequential
from torchrl.collectors import Collector
from torchrl.data import LazyTensorStorage, ReplayBuffer
from torchrl.modules import AdditiveGaussianModule
from torchrl.objectives import SoftUpdate, TD3Loss
from torchrl.record.loggers import get_logger

from recipes import baselines, common
from torchrl_brsl.modules import DampedGaussianModule


def train(cfg: DictConfig, run_dir: str | Path) -> dict:
    """Trains (or resumes) one run; returns the last logged metrics and totals."""
    run_dir = Path(run_dir)
    baseline = baselines.name(cfg)  # None for brsl and td3
    filtered = cfg.method.layer or baseline is not None  # a transform decides the executed action
    if filtered and cfg.method.learn_from not in ("executed", "proposed"):
        raise ValueError(f"method.learn_from must be 'executed' or 'proposed', got {cfg.method.learn_from!r}")
    run_dir.mkdir(parents=True, exist_ok=True)
    OmegaConf.save(cfg, run_dir / "config.yaml", resolve=True)
    common.threads(cfg.threads)
    ckpt_path = run_dir / "checkpoint.pt"
    ckpt = torch.load(ckpt_path, weights_only=False) if cfg.resume and ckpt_path.exists() else None
    frames = ckpt["frames"] if ckpt else 0
    if ckpt is None:  # a fresh run: do not append to the logs of an earlier one
        shutil.rmtree(run_dir / "logs", ignore_errors=True)
        shutil.rmtree(run_dir / "buffer", ignore_errors=True)
    common.seed_everything(cfg.seed + frames)

    # --- the safety layer's reachability models: random-input steps in the empty task, fitted once
    models = None
    if cfg.method.layer:
        if (run_dir / "reach.pt").exists() and ckpt is not None:
            models = common.SafetyModels.load(run_dir)
        else:
            models = common.SafetyModels.fit(cfg, cfg.cache_dir)
            models.save(run_dir)
    elif baseline is not None:
        resume = (run_dir / baselines.FILE).exists() and ckpt is not None
        models = baselines.load(run_dir) if resume else baselines.fit(cfg, cfg.cache_dir)
        baselines.save(models, run_dir)

    # --- env, actor, critics, exploration, (planner)
    env = common.make_env(cfg, cfg.seed + frames, models)
    actor = common.make_actor(env, cfg.hidden)
    qvalue = common.make_qvalue(env, cfg.hidden)
    spec = env.full_action_spec["action"]
    half_range = (spec.space.high - spec.space.low) / 2
    schedules = {"geometric": DampedGaussianModule, "linear": AdditiveGaussianModule}
    if cfg.exploration.schedule not in schedules:
        raise ValueError(f"exploration.schedule must be one of {list(schedules)}, got {cfg.exploration.schedule!r}")
    with warnings.catch_warnings():  # TorchRL copies the per-dim `std` tensor with torch.tensor
        warnings.filterwarnings("ignore", message="To copy construct from a tensor")
        exploration = schedules[cfg.exploration.schedule](spec, sigma_init=float(cfg.exploration.sigma_init),
                                                          sigma_end=float(cfg.exploration.sigma_end),
                                                          annealing_num_steps=cfg.exploration.annealing_frames,
                                                          std=half_range)
    policy = TensorDictSequential(actor, exploration)
    planning = common.make_planner(cfg, policy, env)  # None, or (planner, world model, its loss, optimiser)
    if planning is not None:
        policy = planning[0]  # rolls the noisy actor through the world model, writes `plan` and `action`

    loss = TD3Loss(actor, qvalue, action_spec=spec, num_qvalue_nets=2, policy_noise=cfg.policy_noise,
                   noise_clip=cfg.noise_clip, loss_function="l2")
    loss.make_value_estimator(gamma=cfg.gamma)
    target_update = SoftUpdate(loss, tau=cfg.tau)
    critic_opt = torch.optim.Adam(loss.qvalue_network_params.flatten_keys().values(), lr=cfg.lr_critic)
    actor_opt = torch.optim.Adam(loss.actor_network_params.flatten_keys().values(), lr=cfg.lr_actor)
    buffer = ReplayBuffer(storage=LazyTensorStorage(cfg.buffer_size), batch_size=cfg.batch_size)

    totals = {"frames": frames, "updates": 0, "episodes": 0, "collisions": 0, "interventions": 0, "failsafes": 0}
    if ckpt is not None:
        loss.load_state_dict(ckpt["loss"])
        critic_opt.load_state_dict(ckpt["critic_opt"])
        actor_opt.load_state_dict(ckpt["actor_opt"])
        exploration.load_state_dict(ckpt["exploration"])
        totals.update(ckpt["totals"])
        if planning is not None:
            planning[1].load_state_dict(ckpt["world_model"])
            planning[3].load_state_dict(ckpt["world_model_opt"])
        if (run_dir / "buffer").exists():
            buffer.loads(run_dir / "buffer")

    def save_checkpoint():
        torch.save({"actor": actor.state_dict(), "loss": loss.state_dict(), "critic_opt": critic_opt.state_dict(),
                    "actor_opt": actor_opt.state_dict(), "exploration": exploration.state_dict(),
                    "frames": totals["frames"], "totals": dict(totals),
                    **({"world_model": planning[1].state_dict(), "world_model_opt": planning[3].state_dict()}
                       if planning is not None else {})}, ckpt_path)
        if cfg.checkpoint.save_buffer:
            buffer.dumps(run_dir / "buffer")

    # --- collector: one local process by default; num_collectors / collector_backend to scale out
    remaining = cfg.total_frames - frames
    if remaining <= 0:
        env.close()
        return {"totals": totals, "metrics": {}}
    remote = cfg.num_collectors > 1 or bool(cfg.collector_backend)
    no_registration = {"auto_register_policy_transforms": False}  # the layer belongs to the env, not the policy
    collector_kwargs = dict(no_registration)
    if remote:
        env.close()
        env = _EnvFactory(cfg, cfg.seed + frames, models)
        collector_kwargs = {"num_collectors": cfg.num_collectors, "backend": cfg.collector_backend}
        if cfg.collector_backend == "ray":  # passed on to the remote collectors; weights synced between
            # batches (Ray's weight sync cannot reach an actor that is busy collecting)
            collector_kwargs.update(collector_kwargs=no_registration, sync=True)
        else:
            collector_kwargs.update(no_registration)
    collector = Collector(env, policy, frames_per_batch=cfg.frames_per_batch, total_frames=remaining,
                          init_random_frames=max(0, cfg.init_random_frames - frames), **collector_kwargs)
    if remote:  # distinct seeds per collector process (the single local env is seeded already)
        collector.set_seed(cfg.seed + frames)
        collector.update_policy_weights_()
    logger = get_logger(cfg.logger.backend, logger_name=str(run_dir / "logs"), experiment_name="train",
                        **({"project": cfg.logger.project} if cfg.logger.backend == "wandb" else {})) \
        if cfg.logger.backend else None

    bar = tqdm.tqdm(total=cfg.total_frames, initial=frames, disable=not cfg.progress, desc=str(run_dir))
    next_checkpoint = (frames // cfg.checkpoint.every_frames + 1) * cfg.checkpoint.every_frames
    metrics: dict = {}
    start = time.perf_counter()
    for data in collector:
        data = data.reshape(-1)
        n = data.numel()
        if filtered and cfg.method.learn_from == "executed":
            # learn from what the robot executed (the reward is already penalised by the layer);
            # "proposed" keeps the proposal: the layer is then part of the agent's environment
            data["action"] = data["next", "safe_action"]
        buffer.extend(data.select(*common.BUFFER_KEYS))
        exploration.step(n)
        totals["frames"] += n

        # --- TD3 updates (delayed actor and target updates)
        q_losses, a_losses = [], []
        if totals["frames"] >= cfg.init_random_frames:
            for _ in range(max(1, int(n * cfg.updates_per_frame))):
                batch = buffer.sample()
                q_loss, _ = loss.value_loss(batch)
                critic_opt.zero_grad()
                q_loss.backward()
                critic_opt.step()
                q_losses.append(q_loss.item())
                totals["updates"] += 1
                if totals["updates"] % cfg.policy_delay == 0:
                    a_loss, _ = loss.actor_loss(batch)
                    actor_opt.zero_grad()
                    a_loss.backward()
                    actor_opt.step()
                    a_losses.append(a_loss.item())
                    target_update.step()
        if planning is not None:  # the environment model learns from the same buffer (Algorithm 1)
            from torchrl_brsl.models import train_world_model

            _, model, model_loss, model_opt = planning
            losses = train_world_model(model, model_loss, buffer, cfg.method.ensemble.updates_per_batch, model_opt,
                                       batch_size=cfg.method.ensemble.batch_size)
            metrics_extra = {"train/loss_world_model": losses.mean().item()}
        collector.update_policy_weights_()

        # --- logging
        done = data["next", "done"].squeeze(-1)
        collisions = int(data["next", "collision"].sum())
        totals["episodes"] += int(done.sum())
        totals["collisions"] += collisions
        metrics = {"train/collisions": collisions, "train/collisions_total": totals["collisions"],
                   "train/speed": data["next", "speed"].mean().item(), "train/sigma": exploration.sigma.item(),
                   "train/frames_per_second": (totals["frames"] - frames) / (time.perf_counter() - start)}
        if done.any():
            metrics["train/episode_reward"] = data["next", "episode_reward"][done].mean().item()
        if planning is not None:
            metrics.update(metrics_extra)
        if q_losses:
            metrics["train/loss_qvalue"] = sum(q_losses) / len(q_losses)
        if a_losses:
            metrics["train/loss_actor"] = sum(a_losses) / len(a_losses)
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
        if logger is not None:
            for name, value in metrics.items():
                logger.log_scalar(name, value, step=totals["frames"])
        bar.update(n)
        bar.set_postfix({k.split("/")[1][:12]: round(v, 3) for k, v in metrics.items()
                         if k in ("train/episode_reward", "train/collisions_total", "brsl/intervention_rate")})
        if totals["frames"] >= next_checkpoint:
            save_checkpoint()
            next_checkpoint += cfg.checkpoint.every_frames

    bar.close()
    collector.shutdown()
    save_checkpoint()
    if cfg.eval_after:
        from recipes.evaluate import evaluate_run
        evaluate_run(run_dir)
    return {"totals": totals, "metrics": metrics}


class _EnvFactory:
    """Picklable env constructor for collector processes."""

    def __init__(self, cfg, seed, models):
        self.cfg, self.seed, self.models = cfg, seed, models

    def __call__(self):
        return common.make_env(self.cfg, self.seed, self.models)


@hydra.main(config_path="config", config_name="train", version_base=None)
def main(cfg: DictConfig) -> None:
    result = train(cfg, HydraConfig.get().runtime.output_dir)
    print({k: v for k, v in result["totals"].items()})


if __name__ == "__main__":
    main()
