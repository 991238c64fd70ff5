"""RTS: never returns a parameter whose reachable set meets an obstacle (checked by sampling)."""
import pytest
import torch
from tensordict import TensorDict
from torchrl.envs import SerialEnv, TransformedEnv
from torchrl.envs.utils import check_env_specs

import envs
from torchrl_brsl.baselines import AffineModel, RTSSafeguard, TrajectoryReachableSets, point_clearance
from torchrl_brsl.collision import intersects
from torchrl_brsl.sets import Zonotope

from baselines_support import DT, boxes, double_integrator, velocity_point

LOW, HIGH = -torch.ones(2, dtype=torch.float64), torch.ones(2, dtype=torch.float64)


def _frs(model, **kw):
    options = dict(n_peak=5, n_brk=20, position_dims=(0, 1), action_low=LOW, action_high=HIGH, cells_per_dim=8,
                   braking_gain=torch.tensor([[0, 0, -1 / (20 * DT), 0], [0, 0, 0, -1 / (20 * DT)]]))
    options.update(kw)
    return TrajectoryReachableSets(model, **options)


def test_nominal_trajectory_matches_a_rollout_and_ends_at_rest():
    model, frs = double_integrator(), _frs(double_integrator())
    gen = torch.Generator().manual_seed(0)
    x0 = torch.cat([torch.zeros(6, 2, dtype=torch.float64), 0.5 * torch.randn(6, 2, generator=gen).double()], -1)
    k = frs.cell_center((2 * torch.rand(6, 2, generator=gen) - 1).double())
    actions = frs.actions(x0, k)
    assert torch.allclose(actions[:, :5], k.unsqueeze(1).expand(-1, 5, -1))
    x, positions = x0, []
    for t in range(frs.steps):
        x = model(x, actions[:, t])
        positions.append(x[:, :2])
    exact = frs.sets(x0, k)  # k is its cell's centre: the set's centre is the nominal trajectory
    assert torch.allclose(exact.center, torch.stack(positions, 1), atol=1e-12)
    assert (frs.final_speed_bound(x0, k, velocity_dims=(2, 3)) < 1e-12).all()


@pytest.mark.parametrize("system", ["double_integrator", "velocity_point"])
def test_returned_parameters_have_obstacle_free_reachable_sets_sampled(system):
    """Executed trajectories, sampled over their cell and the bounded model error, never touch a box."""
    residual = 2e-3
    if system == "double_integrator":
        model, frs = double_integrator(residual), _frs(double_integrator(residual))
    else:
        model = velocity_point(residual)
        frs = _frs(model, n_peak=3, n_brk=2, braking_gain=None)
    rts = RTSSafeguard(frs, lambda s: torch.zeros(*s.shape[:-1], 2, dtype=torch.float64), n_samples=15, seed=1)
    gen = torch.Generator().manual_seed(2)
    B = 300
    centers, generators, mask = boxes(B, 4, gen, spread=1.2)
    state = torch.cat([torch.zeros(B, 2, dtype=torch.float64),
                       0.3 * (2 * torch.rand(B, 2, generator=gen, dtype=torch.float64) - 1)], -1)
    if system == "velocity_point":
        state[:, 2:] = 0.0
    clear_start = (point_clearance(state[:, :2], centers, generators, mask) > 0.05).all(-1)
    state, centers, generators, mask = state[clear_start], centers[clear_start], generators[clear_start], \
        mask[clear_start]
    B = state.shape[0]
    action = 2 * torch.rand(B, 2, generator=gen, dtype=torch.float64) - 1
    td = TensorDict({"state": state, "action": action,
                     "obstacles": {"center": centers, "generators": generators, "mask": mask}}, batch_size=[B])
    executed, intervened, flags = rts.filter(td)
    found = ~flags["fallback"]
    assert intervened.any() and (~intervened).any() and found.sum() > B // 2
    plan = td["rts_plan"][found]
    assert torch.allclose(executed[found], plan[:, 0])
    # the chosen parameter is the first action; its cell set misses every obstacle (LP oracle, one step)
    chosen = executed[found]
    sets = frs.sets(state[found], chosen)
    obstacles = Zonotope(centers[found], generators[found])
    t = frs.steps // 2
    hit = intersects(Zonotope(sets.center[:, t].unsqueeze(1).expand(-1, 4, -1),
                              sets.generators[:, t].unsqueeze(1).expand(-1, 4, -1, -1)), obstacles, backend="lp")
    assert not (hit & mask[found]).any()
    # sampled: parameters anywhere in the cell, errors anywhere in the residual box, every step
    width = (HIGH - LOW) / frs.cells_per_dim
    for _ in range(20):
        k = frs.cell_center(chosen) + width * (torch.rand(chosen.shape, generator=gen, dtype=torch.float64) - 0.5)
        u = frs.actions(state[found], k)
        x = state[found]
        for step in range(frs.steps):
            w = residual * (2 * torch.rand(x.shape, generator=gen, dtype=torch.float64) - 1)
            x = model(x, u[:, step]) + w
            clearance = point_clearance(x[:, :2], centers[found], generators[found], mask[found])
            assert (clearance > 0).all(), f"step {step}"
    # proposals whose own cell is safe pass unchanged
    assert torch.equal(executed[~intervened], action[~intervened])


def test_without_a_safe_candidate_the_previous_trajectory_continues():
    model = double_integrator(1e-3)
    frs = _frs(model)
    rts = RTSSafeguard(frs, lambda s: (-s[..., 2:] / DT).clamp(-1, 1), n_samples=5)
    state = torch.tensor([[0.0, 0.0, 0.5, 0.0]], dtype=torch.float64)
    far = {"center": torch.tensor([[[10.0, 0.0]]], dtype=torch.float64),
           "generators": 0.1 * torch.eye(2, dtype=torch.float64).expand(1, 1, 2, 2).clone(),
           "mask": torch.ones(1, 1, dtype=torch.bool)}
    td = TensorDict({"state": state, "action": torch.tensor([[0.4, 0.0]]), "obstacles": far}, batch_size=[1])
    executed, intervened, flags = rts.filter(td)
    assert not intervened.item() and not flags["fallback"].item() and td["rts_plan_step"].item() == 1
    plan = td["rts_plan"].clone()
    # a wall appears just ahead (x >= 0.12): no trajectory stops before it, the stored plan's next row runs
    td["obstacles"] = {"center": torch.tensor([[[1.0, 0.0]]], dtype=torch.float64),
                       "generators": torch.diag(torch.tensor([0.88, 1.0], dtype=torch.float64)).expand(1, 1, 2, 2),
                       "mask": far["mask"]}
    td["state"] = model(state, executed.double())
    executed, intervened, flags = rts.filter(td)
    assert intervened.item() and flags["fallback"].item()
    assert torch.equal(executed, plan[:, 1]) and td["rts_plan_step"].item() == 2


def test_in_the_env_with_specs_and_batched(tmp_path):
    info = envs.safety_info("point_boxes")
    model = AffineModel(torch.eye(4), 0.1 * torch.eye(4, 2), torch.zeros(4), torch.full((4,), 2e-2))
    frs = TrajectoryReachableSets(model, n_peak=2, n_brk=2, position_dims=(0, 1), action_low=info.action_low,
                                  action_high=info.action_high)
    env = TransformedEnv(SerialEnv(2, lambda: envs.make("point_boxes", seed=0)), RTSSafeguard(frs, info.braking_policy))
    check_env_specs(env)
    td = env.rollout(30, break_when_any_done=False)
    assert td["next", "rts_plan"].shape == (2, 30, 4, 2)
    assert td["next", "baseline", "compute_time"].gt(0).all()


def test_bad_options_are_named():
    model = double_integrator()
    with pytest.raises(ValueError, match="n_peak"):
        _frs(model, n_peak=0)
    with pytest.raises(ValueError, match="cells_per_dim"):
        _frs(model, cells_per_dim=0)
    with pytest.raises(ValueError, match="braking_gain"):
        _frs(model, braking_gain=torch.zeros(2, 3))
    with pytest.raises(ValueError, match="action_low"):
        _frs(model, action_low=HIGH, action_high=LOW)
    with pytest.raises(ValueError, match="position_dims"):
        _frs(model, position_dims=(4,))
    with pytest.raises(ValueError, match="n_samples"):
        RTSSafeguard(_frs(model), lambda s: s, n_samples=-1)
