"""Bad numbers are reported per pair as unsafe; malformed arguments raise ``ValueError``."""
from __future__ import annotations

import pytest
import torch
from collision_support import random_polytope, random_zonotope_pairs, stack_sets

from torchrl_brsl.collision import (
    CollisionStatus,
    ZonotopeCollisionChecker,
    check_collision,
    clearance,
    collision_value,
    intersects,
)
from torchrl_brsl.sets import ConstrainedZonotope, Zonotope

F64 = torch.float64


def _box(center, half=1.0):
    center = torch.as_tensor(center, dtype=F64)
    return Zonotope.from_box(center, torch.full_like(center, half))


def test_nan_centre_in_the_hot_path_is_unsafe():
    sets, obstacles = random_zonotope_pairs(seed=0, n=3, num=4, p1=6, p2=3)
    checker = ZonotopeCollisionChecker(sets.generators, obstacles.generators)
    centers = sets.center.clone().requires_grad_()
    poisoned = centers + torch.tensor([0.0, float("nan"), 0.0, float("inf")], dtype=F64).unsqueeze(-1)
    result = checker.check(poisoned, obstacles.center)
    assert result.ok.tolist() == [True, False, True, False]
    assert result.reason_names() == ["OK", "NONFINITE", "OK", "NONFINITE"]
    assert (result.value[~result.ok] == 0).all() and (result.clearance[~result.ok] == 0).all()
    assert (checker.value(poisoned, obstacles.center) == result.value).all()
    assert intersects(sets, obstacles).dtype == torch.bool
    # the poisoned pairs neither raise nor leak NaN into the gradient of the others
    (grad,) = torch.autograd.grad(result.value.sum(), centers)
    assert torch.isfinite(grad).all() and (grad[~result.ok] == 0).all() and (grad[result.ok] != 0).any()


@pytest.mark.parametrize("backend", ["closed_form", "lp"])
def test_nan_in_a_set_is_unsafe_in_check_collision(backend):
    sets, obstacles = random_zonotope_pairs(seed=1, n=2, num=3, p1=4, p2=2)
    sets.center[1, 0] = float("nan")  # tensorclasses validate on construction, not on in-place writes
    obstacles.generators[2, 1, 1] = float("inf")
    result = check_collision(sets, obstacles, backend=backend)
    assert result.reason_names() == ["OK", "NONFINITE", "NONFINITE"]
    assert result.value[0] > 0 and (result.value[1:] == 0).all()
    assert torch.isfinite(result.clearance).all() and (result.clearance[1:] == 0).all()


def test_empty_and_infeasible_obstacles_are_unsafe():
    gen = torch.Generator().manual_seed(2)
    box = _box([0.0, 0.0]).to_constrained()
    far = _box([10.0, 0.0])
    empty = box.intersect_halfspace(torch.tensor([1.0, 0.0], dtype=F64), torch.tensor(-2.0, dtype=F64))  # x <= -2
    assert bool(empty.is_empty())
    # an inconsistent description: a zero constraint row with a non-zero right-hand side
    inconsistent = ConstrainedZonotope(box.center, box.generators, torch.zeros(1, 2, dtype=F64),
                                       torch.ones(1, dtype=F64))
    items = [random_polytope(gen, 2, m=2).translate(torch.tensor([7.0, 0.0], dtype=F64)), empty, inconsistent]
    p, nc = max(o.n_generators for o in items), max(o.n_constraints for o in items)
    obstacles = stack_sets([o.pad(p, nc) for o in items])
    result = check_collision(far, obstacles)
    assert result.reason_names() == ["OK", "EMPTY_SET", "INFEASIBLE"]
    assert result.value[0] > 1 and (result.value[1:] == 0).all()
    assert intersects(far, obstacles).tolist() == [False, True, True]
    assert clearance(far, obstacles)[0] > 0


def test_solver_errors_are_reported_not_raised():
    sets, obstacles = random_zonotope_pairs(seed=3, n=2, num=2, p1=4, p2=2)
    result = check_collision(sets, obstacles, backend="lp", solver_args={"solve_method": "NoSuchSolver"})
    assert result.reason_names() == ["SOLVER_FAILED", "SOLVER_FAILED"]
    assert (result.value == 0).all() and not result.ok.any()
    # an iteration budget too small to converge: the returned point fails the feasibility check
    result = check_collision(sets, obstacles, backend="lp", solver_args={"max_iter": 0})
    assert result.reason_names() == ["SOLVER_FAILED", "SOLVER_FAILED"]


def test_bad_arguments_raise_value_errors_naming_them():
    a = _box([0.0, 0.0])
    with pytest.raises(ValueError, match="`sets`"):
        collision_value(torch.zeros(2), a)
    with pytest.raises(ValueError, match="`obstacles`"):
        collision_value(a, "box")
    with pytest.raises(ValueError, match="`obstacles`.*3-dimensional"):
        collision_value(a, _box([0.0, 0.0, 0.0]))
    with pytest.raises(ValueError, match="`obstacles`.*batch shape"):
        collision_value(_box(torch.zeros(3, 2)), _box(torch.zeros(4, 2)))
    with pytest.raises(ValueError, match="`obstacles`.*dtype"):
        collision_value(a, Zonotope.from_box(torch.zeros(2), torch.ones(2)))
    with pytest.raises(ValueError, match="`backend`"):
        collision_value(a, a, backend="magic")
    with pytest.raises(ValueError, match="`backend`"):
        collision_value(a.to_constrained(), a, backend="closed_form")
    with pytest.raises(ValueError, match="`backend`"):
        collision_value(_box([0.0] * 4), _box([1.0] * 4), backend="closed_form")


def test_checker_rejects_bad_generators_and_centres():
    g = torch.eye(2, dtype=F64)
    with pytest.raises(ValueError, match="`set_generators`"):
        ZonotopeCollisionChecker(torch.zeros(2, dtype=F64), g)
    with pytest.raises(ValueError, match="`obstacle_generators`"):
        ZonotopeCollisionChecker(g, torch.eye(3, dtype=F64))
    with pytest.raises(ValueError, match="`set_generators`.*n in"):
        ZonotopeCollisionChecker(torch.eye(4, dtype=F64), torch.eye(4, dtype=F64))
    with pytest.raises(ValueError, match="`obstacle_generators`"):
        ZonotopeCollisionChecker(g.expand(3, 2, 2), g.expand(4, 2, 2))
    with pytest.raises(ValueError, match="not full-dimensional"):
        ZonotopeCollisionChecker(g[:, :1], g[:, :1])
    with pytest.raises(ValueError, match="`obstacle_generators`"):
        ZonotopeCollisionChecker(g, torch.tensor([[float("nan"), 0.0], [0.0, 1.0]], dtype=F64))
    checker = ZonotopeCollisionChecker(g, g)
    with pytest.raises(ValueError, match="`set_centers`"):
        checker.value(torch.zeros(3, dtype=F64), torch.zeros(2, dtype=F64))
    with pytest.raises(ValueError, match="`obstacle_centers`"):
        checker.check(torch.zeros(2, dtype=F64), torch.zeros(2, 3, dtype=F64))


def test_status_codes_are_stable():
    assert [s.value for s in CollisionStatus] == [0, 1, 2, 3, 4]
    assert [s.name for s in CollisionStatus] == ["OK", "NONFINITE", "EMPTY_SET", "INFEASIBLE", "SOLVER_FAILED"]
