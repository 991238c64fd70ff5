"""SECAS: the corrected action satisfies the linearised constraint; the model learns it from offline data."""
import pytest
import torch
from tensordict import TensorDict
from torchrl.envs import SerialEnv, TransformedEnv
from torchrl.envs.utils import check_env_specs

import envs
from torchrl_brsl.baselines import LinearSafetyModel, SECASSafetyLayer, fit_safety_model, secas_correction
from torchrl_brsl.reach import collect_offline_data


def test_corrected_action_satisfies_the_linearised_constraint():
    gen = torch.Generator().manual_seed(0)
    B, K, m = 500, 3, 2
    action = 2 * torch.rand(B, m, generator=gen, dtype=torch.float64) - 1
    g = torch.randn(B, K, m, generator=gen, dtype=torch.float64)
    c = 0.5 * torch.randn(B, K, generator=gen, dtype=torch.float64)
    mask = torch.rand(B, K, generator=gen) < 0.8
    corrected = secas_correction(action, g, c, mask)
    before = (g * action.unsqueeze(1)).sum(-1) + c
    after = (g * corrected.unsqueeze(1)).sum(-1) + c
    # one constraint: the correction is exact (on the boundary when it was violated)
    single = secas_correction(action, g[:, :1], c[:, :1])
    single_after = (g[:, 0] * single).sum(-1) + c[:, 0]
    assert (single_after <= 1e-12).all()
    violated = before[:, 0] > 0
    assert violated.any() and torch.allclose(single_after[violated], torch.zeros(()).double(), atol=1e-12)
    assert torch.equal(single[~violated], action[~violated])
    # several: the constraint with the largest multiplier is satisfied, masked ones are ignored
    lam = torch.where(mask, (before / (g * g).sum(-1)).clamp_min(0), torch.zeros_like(before))
    top, active = lam.argmax(-1), (lam > 0).any(-1)
    assert active.any() and (after.gather(1, top[:, None]).squeeze(1)[active] <= 1e-12).all()
    # nothing violated (masked constraints do not count): the action passes unchanged
    assert torch.equal(corrected[~active], action[~active])
    assert (torch.where(mask, before, -1.0)[~active] <= 0).all()


def test_the_step_moves_the_action_by_the_smallest_amount_along_g():
    a = torch.tensor([1.0, 1.0])
    g = torch.tensor([[2.0, 0.0]])
    out = secas_correction(a, g, torch.tensor([-1.0]))  # 2 a_x - 1 <= 0 -> a_x = 0.5
    assert torch.allclose(out, torch.tensor([0.5, 1.0], dtype=torch.float64))


@pytest.fixture(scope="module")
def point_boxes_model():
    """g trained on 400 random-input steps of the empty point_boxes and 10 of its layouts."""
    torch.manual_seed(0)
    data = collect_offline_data(envs.make("point_boxes", seed=1, empty=True), 400)
    env = envs.make("point_boxes", seed=2)
    layouts = torch.stack([env.reset()["obstacles"] for _ in range(10)])
    info = envs.safety_info("point_boxes")
    model = LinearSafetyModel(4 + 2 + 2 * layouts["generators"].shape[-1], 2)
    losses = fit_safety_model(model, data, layouts, info.position_dims, steps=1500)
    return model, losses, layouts


def test_fitted_model_predicts_the_clearance_change_of_a_velocity_command(point_boxes_model):
    model, losses, layouts = point_boxes_model
    assert losses[-100:].mean() < 0.2 * losses[:100].mean()
    # the +x wall of a layout, the robot at rest in front of it: the clearance falls by dt * u_x
    # per step; from rest the velocity servo (50 ms lag, 5 m/s^2) covers ~0.025 m at u_x = 1 in the
    # 0.1 s step, so g ~ (+0.025, 0) for c = margin - clearance
    obstacles = layouts[0]
    # (averaged over positions in front of the wall: one MLP fitted to 400 transitions is rough)
    state = torch.zeros(25, 4, dtype=torch.float64)
    state[:, 0], state[:, 1] = torch.linspace(0.8, 1.2, 25), torch.linspace(-0.5, 0.5, 25).flip(0)
    wall = obstacles["center"][:, 0].argmax()
    td = TensorDict({"state": state, "obstacles": {k: v[wall].expand(25, 1, *v[wall].shape) for k, v in
                                                  obstacles.items()}}, batch_size=[25])
    _, g, _ = SECASSafetyLayer(model, position_dims=(0, 1)).constraints(td)
    g = g[:, 0].mean(0)
    assert 0.01 < g[0] < 0.05 and g[0] > g[1].abs()  # mostly along the wall normal


def test_layer_in_the_env_executes_actions_meeting_the_linearised_constraint(point_boxes_model):
    model, _, _ = point_boxes_model
    info = envs.safety_info("point_boxes")
    layer = SECASSafetyLayer(model, position_dims=info.position_dims, margin=0.1)
    env = TransformedEnv(envs.make("point_boxes", seed=3), layer)
    check_env_specs(env)
    td = env.reset()
    corrected = 0
    for _ in range(60):
        td = env.rand_action(td)
        c, g, mask = layer.constraints(td)
        td = env.step(td)
        executed = td["next", "safe_action"].double()
        predicted = torch.where(mask, c + (g * executed.unsqueeze(-2)).sum(-1), -torch.inf)
        lam = torch.where(mask, (c + (g * td["action"].double().unsqueeze(-2)).sum(-1)).clamp_min(0), 0.0)
        if td["next", "baseline", "intervened"].item():
            corrected += 1
            assert predicted[lam.argmax()] <= 1e-6  # the worst constraint holds after correction
        else:
            assert torch.equal(executed, td["action"].double())
        td = env.step_mdp(td) if not td["next", "done"].item() else env.reset()
    assert corrected > 0


def test_batched_envs_and_bad_options(point_boxes_model):
    model, _, _ = point_boxes_model
    env = TransformedEnv(SerialEnv(2, lambda: envs.make("point_boxes", seed=4)),
                         SECASSafetyLayer(model, position_dims=(0, 1), action_low=-torch.ones(2),
                                          action_high=torch.ones(2)))
    check_env_specs(env)
    td = env.rollout(5, break_when_any_done=False)
    assert td["next", "safe_action"].shape == (2, 5, 2) and (td["next", "safe_action"].abs() <= 1).all()
    with pytest.raises(ValueError, match="margin"):
        SECASSafetyLayer(model, position_dims=(0, 1), margin=-1.0)
    with pytest.raises(ValueError, match="position_dims"):
        SECASSafetyLayer(model, position_dims=())
    with pytest.raises(ValueError, match="position_dims"):
        TransformedEnv(envs.make("point_boxes"), SECASSafetyLayer(model, position_dims=(0, 7))).rollout(2)
    with pytest.raises(ValueError, match="steps"):
        fit_safety_model(model, TensorDict(), TensorDict(), (0, 1), steps=0)
    with pytest.raises(ValueError, match="feature_dim"):
        LinearSafetyModel(0, 2)
