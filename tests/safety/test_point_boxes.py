"""The safety guarantee on a MuJoCo point mass among boxes (ground truth: MuJoCo contacts)."""
import functools

import pytest
import torch
from torchrl.envs import SerialEnv, TransformedEnv

from torchrl_brsl.safety import FacetQPAdjuster

from safety_support import make_env, make_layer

TASK = "point_boxes"
N_ENVS = 10
EPISODE = 60


def batched(with_layer: bool, seed: int = 0, **layer_kwargs):
    base = SerialEnv(N_ENVS, [functools.partial(make_env, TASK, seed=seed + i, episode_steps=EPISODE)
                              for i in range(N_ENVS)])
    return TransformedEnv(base, make_layer(TASK, **layer_kwargs)) if with_layer else base


def random_policy(td):
    td["action"] = torch.rand(*td.batch_size, 2) * 2 - 1
    return td


def nearest_obstacle_policy(td):
    """Adversarial: full speed towards the nearest real obstacle."""
    position = td["state"][..., :2]
    centers = td["obstacles", "center"]
    distance = (centers - position.unsqueeze(-2)).norm(dim=-1)
    distance = torch.where(td["obstacles", "mask"], distance, torch.full_like(distance, float("inf")))
    target = centers.gather(-2, distance.argmin(-1, keepdim=True).unsqueeze(-1).expand(-1, 1, 2)).squeeze(-2)
    direction = target - position
    td["action"] = direction / direction.abs().amax(-1, keepdim=True).clamp_min(1e-6)
    return td


def run_episodes(env, policy, n_episodes: int):
    """Episodes of the batched env with per-env resets; returns (collided per episode, mean speed)."""
    td = env.reset()
    collided, current = [], torch.zeros(N_ENVS, dtype=torch.bool)
    speeds = []
    while len(collided) < n_episodes:
        td = env.step(policy(td))
        current |= td["next", "collision"].squeeze(-1)
        speeds.append(td["next", "speed"].squeeze(-1))
        done = td["next", "done"].squeeze(-1)
        collided += current[done].tolist()
        current[done] = False
        td = env.step_mdp(td)
        if done.any():
            td["_reset"] = done.unsqueeze(-1)
            td = env.reset(td)
    return torch.tensor(collided[:n_episodes]), torch.cat(speeds).mean().item()


@pytest.fixture(scope="module")
def unprotected_random():
    return run_episodes(batched(False), random_policy, 200)


def test_random_policy_without_the_layer_collides_in_most_episodes(unprotected_random, capsys):
    collided, speed = unprotected_random
    with capsys.disabled():
        print(f"\n[{TASK}] random policy, no layer: {int(collided.sum())}/200 episodes collided, "
              f"mean speed {speed:.3f} m/s")
    assert collided.float().mean() > 0.5


@pytest.mark.parametrize("adjuster", ["gradient", "facet_qp"])
def test_random_policy_behind_the_layer_never_collides(adjuster, unprotected_random, capsys):
    kwargs = {"adjuster": FacetQPAdjuster()} if adjuster == "facet_qp" else {}
    collided, speed = run_episodes(batched(True, **kwargs), random_policy, 200)
    with capsys.disabled():
        print(f"\n[{TASK}] random policy behind the layer ({adjuster}): {int(collided.sum())}/200 episodes "
              f"collided, mean speed {speed:.3f} m/s")
    assert len(collided) == 200
    assert not collided.any(), f"{int(collided.sum())} of 200 episodes collided behind the layer"
    # the layer does not buy safety by freezing the robot
    assert speed > 0.25 * unprotected_random[1]


def test_adversarial_policy_behind_the_layer_never_collides():
    unprotected, _ = run_episodes(batched(False, seed=100), nearest_obstacle_policy, 40)
    assert unprotected.float().mean() > 0.8
    collided, speed = run_episodes(batched(True, seed=100, adjuster=FacetQPAdjuster()), nearest_obstacle_policy, 40)
    assert not collided.any()
    assert speed > 0.05
