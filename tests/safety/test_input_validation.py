"""Malformed input: a wrong structure is a ValueError naming the key and both shapes; wrong values
mid-episode never crash, execute a verified action and are flagged (``invalid_input``, and
``intervened`` whenever the executed action differs from the proposal).

Every case edits the TensorDict of ``point_boxes`` before ``env.step``, as a user's env or policy
would produce it.
"""
import functools

import pytest
import torch
from hypothesis import HealthCheck, event, given, settings
from hypothesis import strategies as st
from tensordict import TensorDict
from torchrl.envs import SerialEnv, TransformedEnv

import envs
from torchrl_brsl.safety import FacetQPAdjuster

from safety_support import make_env, make_layer

TASK = "point_boxes"
INFO = envs.safety_info(TASK)


@functools.lru_cache(maxsize=None)
def _env_and_start():
    """The layered env and a TensorDict one verified step into an episode (a safe plan exists)."""
    torch.set_num_threads(1)
    env = TransformedEnv(make_env(TASK, seed=0), make_layer(TASK))
    td = env.reset()
    td["action"] = torch.tensor([0.3, 0.0])
    td = env.step_mdp(env.step(td))
    assert not td["brsl", "failsafe"].item()
    return env, td


def start():
    env, td = _env_and_start()
    td = td.clone()
    td["action"] = torch.tensor([0.2, 0.1])
    return env, td


def obstacle_slots(td, k):
    td["obstacles"] = TensorDict(center=td["obstacles", "center"][:k], generators=td["obstacles", "generators"][:k],
                                 mask=td["obstacles", "mask"][:k])


# ----------------------------------------------------------------- the cases of the issue
def test_mask_of_a_different_length_names_the_key_and_both_shapes():
    env, td = start()
    k = td["obstacles", "mask"].shape[-1]
    td["obstacles", "mask"] = td["obstacles", "mask"][: k - 2].clone()
    with pytest.raises(ValueError, match=rf"`obstacles/mask` has shape \({k - 2},\), expected \({k},\).*"
                                         rf"`obstacles/center` \({k}, 2\)"):
        env.step(td)


def test_centres_and_generators_of_different_k_name_the_key_and_both_shapes():
    env, td = start()
    k = td["obstacles", "center"].shape[-2]
    td["obstacles"] = TensorDict(center=td["obstacles", "center"][: k - 2], generators=td["obstacles", "generators"],
                                 mask=td["obstacles", "mask"][: k - 2])
    with pytest.raises(ValueError, match=rf"`obstacles/generators` has shape \({k}, 2, 6\), expected \({k - 2}, 2, \*\)"):
        env.step(td)


def test_obstacles_of_the_wrong_dimension_name_the_obstacle_space():
    env, td = start()
    k = td["obstacles", "center"].shape[-2]
    td["obstacles"] = TensorDict(center=torch.zeros(k, 3, dtype=torch.float64),
                                 generators=torch.zeros(k, 3, 7, dtype=torch.float64), mask=td["obstacles", "mask"])
    with pytest.raises(ValueError, match=r"`obstacles/center` has shape \(10, 3\), expected \(\*, 2\).*obstacle space"):
        env.step(td)


def test_action_of_the_wrong_size_names_the_models_action_dim():
    env, td = start()
    td["action"] = torch.tensor([0.1, 0.0, 0.0])
    with pytest.raises(ValueError, match=r"`action` has shape \(3,\), expected \(2,\).*action_dim=2"):
        env.step(td)


def test_plan_of_the_wrong_action_size_is_a_clear_error():
    env, td = start()
    td["plan"] = torch.zeros(3, 5)
    with pytest.raises(ValueError, match=r"`plan` has shape \(3, 5\), expected \(\*, 2\)"):
        env.step(td)


def test_state_of_the_wrong_size_names_the_models_state_dim():
    env, td = start()
    td["state"] = torch.zeros(6, dtype=torch.float64)
    with pytest.raises(ValueError, match=r"`state` has shape \(6,\), expected \(4,\).*state_dim=4"):
        env.step(td)


@pytest.mark.parametrize("key, value, message", [
    ("action", torch.tensor([1, 0]), "`action` must be a floating-point tensor, got torch.int64"),
    ("state", torch.zeros(4, dtype=torch.int64), "`state` must be a floating-point tensor"),
    (("obstacles", "mask"), torch.ones(10), "`obstacles/mask` must be a bool tensor"),
    (("obstacles", "center"), torch.zeros(10, 2, dtype=torch.int64), "`obstacles/center` must be a floating-point"),
])
def test_wrong_dtypes_are_clear_errors(key, value, message):
    env, td = start()
    td[key] = value
    with pytest.raises(ValueError, match=message):
        env.step(td)


def test_missing_obstacle_entry_is_a_clear_error():
    env, td = start()
    del td["obstacles", "generators"]
    with pytest.raises(ValueError, match="`obstacles/generators`"):
        env.step(td)


@pytest.mark.parametrize("adjuster", ["gradient", "facet_qp"])
def test_zero_obstacle_slots_work(adjuster):
    env = TransformedEnv(make_env(TASK, seed=0), make_layer(TASK, adjuster=adjuster))
    td = env.reset()
    for action in ([0.3, 0.0], [1.0, 1.0], [-1.0, 0.5]):
        obstacle_slots(td, 0)
        td["action"] = torch.tensor(action)
        td = env.step(td)
        assert td["next", "brsl", "min_collision_value"].item() == float("inf")
        assert torch.isfinite(td["next", "safe_action"]).all()
        td = env.step_mdp(td)


def test_action_far_outside_the_bounds_is_clamped_verified_and_flagged():
    env, td = start()
    td["action"] = torch.tensor([7.0, -3.5])
    out = env.step(td)["next"]
    executed = out["safe_action"]
    assert torch.all(executed >= INFO.action_low) and torch.all(executed <= INFO.action_high)
    assert out["brsl", "intervened"].item()  # not executed as proposed
    assert out["brsl", "invalid_input"].item()
    # the clamped proposal was verified (or the failsafe took over): the executed action is the
    # first of the plan the layer now holds as verified
    assert out["safe_plan_steps"].item() > 0


def test_action_on_the_bound_is_neither_invalid_nor_an_intervention():
    env, td = start()
    td["obstacles", "mask"] = torch.zeros_like(td["obstacles", "mask"])
    td["action"] = torch.tensor([0.0, 0.0])
    td["action"][0] = INFO.action_high[0]
    out = env.step(td)["next"]
    assert not out["brsl", "invalid_input"].item()
    assert out["brsl", "intervened"].item() == (not torch.equal(out["safe_action"], td["action"]))


@pytest.mark.parametrize("key", ["state", "action", ("obstacles", "center"), ("obstacles", "generators")])
@pytest.mark.parametrize("value", [float("nan"), float("inf"), -float("inf")])
def test_non_finite_values_execute_the_verified_plan_and_are_flagged(key, value):
    env, td = start()
    expected = td["safe_plan"][0].to(torch.float32)
    if isinstance(key, tuple):  # in a real obstacle
        assert td["obstacles", "mask"][0]
        td[key][0].view(-1)[0] = value
    else:
        td[key].view(-1)[0] = value
    out = env.step(td)["next"]
    assert out["brsl", "invalid_input"].item() and out["brsl", "intervened"].item()
    assert out["brsl", "failsafe"].item()
    assert torch.equal(out["safe_action"], expected)


def test_non_finite_values_in_an_empty_slot_are_ignored():
    env, td = start()
    td["obstacles", "mask"][-1] = False
    td["obstacles", "center"][-1] = float("nan")
    out = env.step(td)["next"]
    assert not out["brsl", "invalid_input"].item()


def test_a_batch_flags_only_the_env_with_invalid_values():
    env = TransformedEnv(SerialEnv(2, [functools.partial(make_env, TASK, seed=i) for i in range(2)]),
                         make_layer(TASK, adjuster=FacetQPAdjuster()))
    td = env.reset()
    td["action"] = torch.tensor([[0.2, 0.0], [0.2, 0.0]])
    td["obstacles", "center"][1, 0, 0] = float("nan")
    out = env.step(td)["next", "brsl"]
    assert out["invalid_input"].squeeze(-1).tolist() == [False, True]
    k = td["obstacles", "mask"].shape[-1]
    td["obstacles", "mask"] = td["obstacles", "mask"][:, : k - 1].clone()
    with pytest.raises(ValueError, match=rf"`obstacles/mask` has shape \(2, {k - 1}\), expected \(2, {k}\)"):
        env.step(td)


def test_a_model_of_another_robot_is_refused_at_construction():
    with pytest.raises(ValueError, match=r"`state` has shape \(6,\), expected \(4,\)"):
        TransformedEnv(envs.make("diffdrive_nav", seed=0), make_layer(TASK))


def test_bad_bounds_and_dims_are_refused_at_construction():
    with pytest.raises(ValueError, match="action_low"):
        make_layer(TASK, action_low=torch.zeros(3), action_high=torch.ones(3))
    with pytest.raises(ValueError, match="exceeds"):
        make_layer(TASK, action_low=torch.ones(2), action_high=-torch.ones(2))
    with pytest.raises(ValueError, match="stop_dims"):
        make_layer(TASK, stop_dims=(2, 7))


# ----------------------------------------------------------------- property: clear error or flagged safe action
ENTRIES = ["state", "action", "plan", ("obstacles", "center"), ("obstacles", "generators"), ("obstacles", "mask")]
VALUES = [float("nan"), float("inf"), -float("inf"), 7.0, -3.5, 1e30, 0.0]


@st.composite
def mutations(draw):
    """One or two edits of the TensorDict: a structural one (shape, dtype) or a value."""
    edits = []
    for _ in range(draw(st.integers(1, 2))):
        key = draw(st.sampled_from(ENTRIES))
        kind = draw(st.sampled_from(["grow", "shrink", "lead", "dtype", "value", "value", "value", "slots"]))
        edits.append((key, kind, draw(st.integers(0, 10_000)), draw(st.sampled_from(VALUES))))
    return edits


def _apply(td, edit):
    """Returns ``(structural, non_finite_or_out_of_bounds)`` for the edit."""
    key, kind, where, value = edit
    if key == "plan" and "plan" not in td.keys():
        td["plan"] = td["action"].unsqueeze(0).expand(3, -1).clone()
    tensor = td[key]
    if kind == "slots":  # K obstacle slots, from 0 to K + 2, consistent across the three entries
        k = where % (tensor.shape[0] + 3) if key[0] == "obstacles" else None
        if k is None:
            return False, False
        pad = max(0, k - td["obstacles", "mask"].shape[-1])
        td["obstacles"] = TensorDict(
            center=torch.cat((td["obstacles", "center"], torch.zeros(pad, 2, dtype=torch.float64)))[:k],
            generators=torch.cat((td["obstacles", "generators"], torch.zeros(pad, 2, 6, dtype=torch.float64)))[:k],
            mask=torch.cat((td["obstacles", "mask"], torch.zeros(pad, dtype=torch.bool)))[:k])
        return False, False
    if kind in ("grow", "shrink"):
        axis = where % tensor.ndim
        if kind == "grow":
            tensor = torch.cat((tensor, tensor.narrow(axis, 0, 1)), dim=axis)
        elif tensor.shape[axis] > 1:
            tensor = tensor.narrow(axis, 0, tensor.shape[axis] - 1)
        else:
            return False, False
        if key == "plan" and axis == 0 and tensor.shape[0] <= INFO.n_plan:  # another plan length in 1..n_plan is valid
            td[key] = tensor
            return False, False
        td.set(key, tensor)
        return True, False
    if kind == "lead":
        td.set(key, tensor.unsqueeze(0))
        return True, False
    if kind == "dtype":
        td[key] = tensor.to(torch.float32 if tensor.dtype is torch.bool else torch.int64)
        return True, False
    if tensor.dtype is torch.bool or tensor.numel() == 0:
        return False, False
    flat = tensor.clone().view(-1)
    index = where % flat.numel()
    flat[index] = value
    td[key] = flat.view(tensor.shape)
    if key[0] == "obstacles":  # only real obstacles count; which slot the entry is in:
        per_slot = flat.numel() // tensor.shape[0]
        counts = bool(td["obstacles", "mask"][index // per_slot])
    else:
        counts = True
    bad = not torch.isfinite(torch.tensor(value)) or (key in ("action", "plan") and abs(value) > 1.0)
    return False, counts and bad


@settings(max_examples=40, deadline=None, derandomize=True, suppress_health_check=list(HealthCheck))
@given(mutations())
def test_property_clear_error_or_flagged_safe_action(edits):
    env, td = start()
    structural, invalid = False, False
    for edit in edits:
        s, v = _apply(td, edit)
        structural, invalid = structural or s, invalid or v
    proposal = (td["plan"][0] if "plan" in td.keys() else td["action"]).clone()
    try:
        out = env.step(td)["next"]
    except ValueError as err:  # a clear error: it names the key and shows the shape it got
        assert structural, f"a ValueError for values only: {err}"
        message = str(err)
        assert any(f"`{k if isinstance(k, str) else '/'.join(k)}`" in message for k, *_ in edits), message
        event("clear ValueError")
        return
    assert not structural or _still_valid(td), "a malformed structure passed silently"
    executed = out["safe_action"]
    assert executed.shape == (2,) and torch.isfinite(executed).all()
    assert torch.all(executed >= INFO.action_low) and torch.all(executed <= INFO.action_high)
    brsl = out["brsl"]
    if invalid:
        assert brsl["invalid_input"].item()
    if not torch.equal(executed, proposal.to(executed.dtype)):
        assert brsl["intervened"].item()
    event("invalid values, flagged" if invalid else "valid values")


def _still_valid(td):
    """A structural edit the layer accepts must leave a well-formed input (e.g. a shorter plan)."""
    k = td["obstacles", "center"].shape[-2]
    return (td["state"].shape == (4,) and td["action"].shape == (2,) and td["obstacles", "mask"].shape == (k,)
            and td["obstacles", "generators"].shape[:-1] == (k, 2))


def test_a_corrupted_stored_safe_plan_never_reaches_the_robot():
    env, td = start()
    td["safe_plan"] = torch.full_like(td["safe_plan"], float("nan"))
    td["obstacles", "center"][0] = td["state"][:2]  # nothing verifies: the fallback would be the stored plan
    out = env.step(td)["next"]
    assert out["brsl", "invalid_input"].item() and out["brsl", "failsafe"].item()
    assert torch.isfinite(out["safe_action"]).all() and torch.isfinite(out["safe_plan"]).all()
    assert torch.equal(out["safe_action"], torch.zeros(2))  # the hold action


@pytest.mark.parametrize("key, value, message", [
    ("safe_plan", torch.zeros(3, 2, dtype=torch.float64), r"`safe_plan` has shape \(3, 2\), expected \(9, 2\)"),
    ("safe_plan_steps", torch.zeros(1), "`safe_plan_steps` must be an integer tensor"),
])
def test_a_malformed_stored_safe_plan_is_a_clear_error(key, value, message):
    env, td = start()
    td[key] = value
    with pytest.raises(ValueError, match=message):
        env.step(td)


# ----------------------------------------------------------------- property, batched: one env's bad values stay its own
VALUE_ENTRIES = ["state", "action", ("obstacles", "center"), ("obstacles", "generators")]


@functools.lru_cache(maxsize=None)
def _batched_start():
    """A layer outside a ``SerialEnv`` of 2, and a TensorDict one verified step into the episodes."""
    torch.set_num_threads(1)
    env = TransformedEnv(SerialEnv(2, functools.partial(make_env, TASK, seed=0)), make_layer(TASK))
    td = env.reset()
    td["action"] = torch.tensor([[0.3, 0.0], [0.2, -0.1]])
    td = env.step_mdp(env.step(td))
    assert not td["brsl", "failsafe"].any()
    return env, td


@settings(max_examples=25, deadline=None, derandomize=True, suppress_health_check=list(HealthCheck))
@given(st.integers(0, 1), st.sampled_from(VALUE_ENTRIES), st.integers(0, 10_000), st.sampled_from(VALUES))
def test_property_batched_bad_values_are_flagged_where_they_are_and_nowhere_else(env_index, key, where, value):
    """The layer serves both envs in one call: a bad value in one env is flagged there (and never executed),
    and the other env's decision is exactly the one it gets without the edit."""
    env, td = _batched_start()
    td = td.clone()
    reference = env.transform.inv(td.clone())
    edited = td[key][env_index].clone().view(-1)
    edited[where % edited.numel()] = value
    td[key][env_index] = edited.view(td[key][env_index].shape)
    if key[0] == "obstacles":  # only real obstacles count; which slot the entry is in:
        slot = (where % edited.numel()) // (edited.numel() // td["obstacles", "mask"].shape[-1])
        counts = bool(td["obstacles", "mask"][env_index, slot])
    else:
        counts = True
    invalid = counts and (not torch.isfinite(torch.tensor(value)) or (key == "action" and abs(value) > 1.0))
    out = env.transform.inv(td)
    executed = out["action"]
    assert torch.isfinite(executed).all()
    assert torch.all(executed >= INFO.action_low) and torch.all(executed <= INFO.action_high)
    if invalid:
        assert out["brsl", "invalid_input"][env_index].item()
    other = 1 - env_index
    assert torch.equal(executed[other], reference["action"][other])
    for name in ("intervened", "failsafe", "invalid_input", "unverified_hold"):
        assert torch.equal(out["brsl", name][other], reference["brsl", name][other]), name
    event("invalid, flagged" if invalid else "valid")


def test_polytope_constraints_come_together_and_match_the_obstacles():
    env, td = start()
    k, p = td["obstacles", "generators"].shape[-3], td["obstacles", "generators"].shape[-1]
    alone = td.clone()
    alone["obstacles", "constraint_matrix"] = torch.zeros(k, 2, p, dtype=torch.float64)
    with pytest.raises(ValueError, match="constraint_offset"):
        env.step(alone)
    mismatched = alone.clone()
    mismatched["obstacles", "constraint_offset"] = torch.zeros(k, 3, dtype=torch.float64)  # 3 rows, not 2
    with pytest.raises(ValueError, match=rf"`obstacles/constraint_offset` has shape \({k}, 3\), expected \({k}, 2\)"):
        env.step(mismatched)
