import copy
import functools

import pytest
import torch
from tensordict import TensorDict
from torchrl.envs import ParallelEnv, SerialEnv, TransformedEnv
from torch._dynamo.utils import counters
from torch._subclasses.fake_tensor import FakeTensorMode
from torchrl.envs.utils import check_env_specs

import envs
from torchrl_brsl.safety import DIAGNOSTICS, BRSLSafetyLayer, Failsafe

from safety_support import fitted_reach, make_layer

TASK = "diffdrive_nav"


def layered_env(task=TASK, seed=0, **kwargs):
    return TransformedEnv(envs.make(task, seed=seed), make_layer(task, **kwargs))


def test_check_env_specs_single_env():
    check_env_specs(layered_env())


def test_check_env_specs_serial_env_with_layer_outside():
    env = TransformedEnv(SerialEnv(2, functools.partial(envs.make, TASK, seed=0)), make_layer(TASK))
    check_env_specs(env)
    td = env.rollout(5, break_when_any_done=False)
    assert td["next", "safe_action"].shape == (2, 5, 2)
    assert td["next", "safe_plan"].shape == (2, 5, 14, 2)


def test_parallel_env_with_layer_outside():
    env = TransformedEnv(ParallelEnv(2, functools.partial(envs.make, TASK, seed=0), mp_start_method="fork"),
                         make_layer(TASK))
    try:
        td = env.rollout(4, break_when_any_done=False)
    finally:
        env.close()
    assert td["next", "brsl", "compute_time"].shape == (2, 4, 1)
    assert not td["next", "collision"].any()


def test_load_state_dict_rebuilds_the_checkers_from_the_loaded_model():
    """The checker's tables (the global model's affine rollouts, built at the first step) follow a loaded model."""
    layer = copy.deepcopy(make_layer(TASK))  # a copy: the session's fitted model stays as it is
    td = TransformedEnv(envs.make(TASK, seed=0), layer).rollout(3)
    x0, plan = td["next", "state"][-1:].double(), torch.tensor([[[0.1, 0.2]]], dtype=torch.float64)
    checked = layer.checker
    state = layer.state_dict()
    state["reach.offset"] = state["reach.offset"] + 0.01  # a drift of 1 cm a step
    layer.load_state_dict(state)
    actions, centers = layer.checker.rollout(x0, plan)
    assert layer.checker is not checked and layer.decision.checker is layer.checker
    torch.testing.assert_close(centers, layer.reach.reach_centers(x0, actions), rtol=0, atol=1e-12)


def test_a_move_rebuilds_the_checkers_on_the_models_new_dtype():
    """``.to()`` that moves or casts the model rebuilds the checkers on it (a dtype stands in for a device here);
    one that changes nothing keeps them."""
    layer = copy.deepcopy(make_layer(TASK))
    TransformedEnv(envs.make(TASK, seed=0), layer)  # appended: the obstacle shapes to prepare for are kept
    checked, prepared = layer.checker, layer._prepared
    layer.to(torch.float64)
    assert layer.checker is checked and layer._prepared is prepared
    layer.to(torch.float32)
    assert layer.checker is not checked and layer.checker.action_low.dtype == torch.float32
    assert layer._prepared is not prepared and layer._prepared.center.device == layer.reach.state_matrix.device


def test_writes_executed_action_and_diagnostics_on_reset_and_step():
    env = layered_env()
    td = env.reset()
    assert td["safe_plan"].shape == (14, 2)
    assert torch.equal(td["safe_plan"], torch.zeros(14, 2, dtype=torch.float64))  # stay stopped at start
    for name in DIAGNOSTICS:
        assert td["brsl", name].shape == (1,)
    td = env.rollout(10)
    executed = td["next", "safe_action"]
    low, high = envs.safety_info(TASK).action_low, envs.safety_info(TASK).action_high
    assert torch.all(executed >= low) and torch.all(executed <= high)
    # what was executed is the first action of the plan kept for the next step, shifted
    proposed_ok = ~td["next", "brsl", "intervened"].squeeze(-1)
    assert torch.allclose(executed[proposed_ok], td["action"][proposed_ok].clamp(low, high))


def test_executed_action_is_what_the_robot_receives():
    """The base env must receive the layer's action, not the proposal."""
    seen = []

    base = envs.make(TASK, seed=0)
    original = base._step

    def recording_step(tensordict):
        seen.append(tensordict["action"].clone())
        return original(tensordict)

    base._step = recording_step
    env = TransformedEnv(base, make_layer(TASK))
    td = env.reset()
    td["action"] = torch.tensor([0.25, 0.5])  # full speed and turn: the layer may change it
    td = env.step(td)
    assert torch.equal(seen[-1], td["next", "safe_action"])


def test_partial_reset_keeps_other_envs_safe_plans():
    env = TransformedEnv(SerialEnv(2, functools.partial(envs.make, TASK, seed=0)), make_layer(TASK))
    td = env.reset()
    td["plan"] = torch.tensor([[0.2, 0.3], [0.2, -0.3]]).unsqueeze(1).expand(2, 8, 2)
    td["action"] = td["plan"][:, 0]
    td = env.step_mdp(env.step(td))
    plans = td["safe_plan"].clone()
    assert not torch.equal(plans[1], torch.zeros_like(plans[1]))
    td["_reset"] = torch.tensor([[True], [False]])
    out = env.reset(td)
    assert torch.equal(out["safe_plan"][0], torch.zeros_like(plans[0]))
    assert torch.equal(out["safe_plan"][1], plans[1])


@pytest.mark.parametrize("where", ["state", "action", "plan"])
def test_non_finite_input_gives_failsafe_and_flag(where):
    env = layered_env()
    td = env.reset()
    td["plan"] = torch.tensor([[0.2, 0.0]] * 8)
    td["action"] = td["plan"][0]
    td = env.step_mdp(env.step(td))  # now a non-trivial safe plan exists
    assert not torch.equal(td["safe_plan"][0], torch.zeros(2, dtype=torch.float64))
    del td["plan"]
    expected = td["safe_plan"][0].to(torch.float32)
    td["action"] = torch.tensor([0.1, 0.1])
    if where == "state":
        td["state"] = torch.full_like(td["state"], float("nan"))
    elif where == "action":
        td["action"] = torch.tensor([float("inf"), 0.0])
    else:
        td["plan"] = torch.full((8, 2), float("nan"))
    out = env.step(td)
    assert out["next", "brsl", "invalid_input"].item()
    assert out["next", "brsl", "failsafe"].item()
    assert torch.equal(out["next", "safe_action"], expected)
    assert torch.isfinite(out["next", "safe_action"]).all()


def test_wrong_obstacle_shape_is_a_clear_error():
    env = layered_env()
    td = env.reset()
    td["obstacles"] = TensorDict(center=torch.zeros(12, 3), generators=torch.zeros(12, 3, 6),
                                 mask=torch.ones(12, dtype=torch.bool))
    td["action"] = torch.tensor([0.1, 0.0])
    with pytest.raises(ValueError, match="obstacles/center"):
        env.step(td)


def test_without_obstacles_a_stopping_plan_is_accepted():
    env = layered_env()
    td = env.reset()
    td["obstacles", "mask"] = torch.zeros_like(td["obstacles", "mask"])
    td["plan"] = torch.tensor([[0.1, 0.0]] * 8)
    td["action"] = td["plan"][0]
    out = env.step(td)
    assert not out["next", "brsl", "intervened"].item()
    assert out["next", "brsl", "min_collision_value"].item() == float("inf")
    assert torch.allclose(out["next", "safe_plan"][:7].float(), td["plan"][1:])


def test_plan_longer_than_n_plan_is_rejected():
    env = layered_env()
    td = env.reset()
    td["plan"] = torch.zeros(9, 2)
    with pytest.raises(ValueError, match="n_plan"):
        env.step(td)


def test_penalty_lowers_the_reward_of_unsafe_proposals():
    env = layered_env(penalty=5.0)
    plain = envs.make(TASK, seed=0)
    td, ref = env.reset(), plain.reset()
    td["obstacles", "center"][0] = td["state"][:2] + torch.tensor([0.3, 0.0])
    td["obstacles", "mask"][0] = True
    td["action"] = torch.tensor([0.25, 0.0])
    out = env.step(td)
    assert out["next", "brsl", "intervened"].item()
    ref["action"] = out["next", "safe_action"]
    assert torch.isclose(out["next", "reward"], plain.step(ref)["next", "reward"] - 5.0)


def test_constructor_rejects_bad_arguments():
    info = envs.safety_info(TASK)
    reach = fitted_reach(TASK)
    brake = Failsafe(info.braking_action, info.n_brk)
    with pytest.raises(ValueError, match="stop_tolerance"):
        BRSLSafetyLayer(reach, brake, 8, stop_dims=(4, 5), stop_tolerance=1e-3, action_low=info.action_low,
                        action_high=info.action_high)
    with pytest.raises(ValueError, match="n_plan"):
        BRSLSafetyLayer(reach, brake, 0, stop_dims=(4, 5), stop_tolerance=10.0)
    with pytest.raises(ValueError, match="reach"):
        BRSLSafetyLayer(object(), brake, 8, stop_dims=(4, 5), stop_tolerance=10.0)
    with pytest.raises(ValueError, match="hold_action"):
        BRSLSafetyLayer(reach, Failsafe(torch.zeros(3), 6), 8, stop_dims=(4, 5), stop_tolerance=10.0)


def test_adjuster_by_name():
    assert type(make_layer(TASK, adjuster="facet_qp").adjuster).__name__ == "FacetQPAdjuster"
    assert make_layer(TASK, adjuster=None).adjuster is None
    with pytest.raises(ValueError, match="adjuster"):
        make_layer(TASK, adjuster="newton")


def test_holding_beyond_every_verified_plan_is_flagged():
    env = layered_env()
    td = env.reset()
    assert not td["brsl", "unverified_hold"].item()
    td["action"] = torch.tensor([0.1, 0.0])
    free = env.step(td.clone())["next", "brsl"]
    assert not free["failsafe"].item() and not free["unverified_hold"].item()
    # an obstacle on the robot: nothing verifies, and at episode start no verified plan is left
    td["obstacles", "center"][0] = td["state"][:2].to(td["obstacles", "center"].dtype)
    td["obstacles", "mask"][0] = True
    blocked = env.step(td)["next"]
    assert blocked["brsl", "failsafe"].item() and blocked["brsl", "unverified_hold"].item()
    assert torch.equal(blocked["safe_action"], torch.zeros(2))


@pytest.mark.filterwarnings("ignore:the stop check certifies nothing")  # 500 steps of the capped servos: wide sets
def test_a_compiled_local_model_compiles_its_checks_when_appended_to_the_env():
    """The closed-form check of a compiled local model is compiled for the env's obstacle shapes when the layer is
    appended to the env (``PlanChecker.prepare_checks``), not at the first control step."""
    info = envs.safety_info(TASK)
    reach = copy.deepcopy(fitted_reach(TASK, method="local")).compile_steps(backend="aot_eager")
    layer = BRSLSafetyLayer(reach, Failsafe(info.braking_action, info.n_brk), info.n_plan, stop_dims=info.velocity_dims,
                            action_low=info.action_low, action_high=info.action_high)
    frames, misses = counters["frames"]["ok"], FakeTensorMode.cache_misses
    env = TransformedEnv(envs.make(TASK, seed=0), layer)
    assert counters["frames"]["ok"] > frames
    assert FakeTensorMode.cache_misses == misses  # traced without the fake-tensor cache (quick_tracing)
    frames = counters["frames"]["ok"]
    td = env.rollout(3)
    assert counters["frames"]["ok"] == frames and not td["next", "collision"].any()
