"""The HiGHS reference LPs: a problem whose numerics stop HiGHS's default method is solved by its interior point."""
from types import SimpleNamespace

import numpy as np
from scipy.optimize import linprog

from torchrl_brsl.sets import lp


def test_the_gauge_is_solved_by_the_interior_point_where_the_default_method_gives_up(monkeypatch):
    """As on a capped quadrotor's 6 x 30 gauge problem, where the dual simplex stopped with "Not Set"."""
    calls = []

    def default_gives_up(cost, method, **problem):
        calls.append(method)
        if method == "highs":
            return SimpleNamespace(status=lp.NUMERICAL_DIFFICULTIES, message="(HiGHS Status 0: Not Set)")
        return linprog(cost, method=method, **problem)

    monkeypatch.setattr(lp, "linprog", default_gives_up)
    A, b = np.array([[1.0, 0.0, 1.0], [0.0, 1.0, 1.0]]), np.array([0.5, 0.5])
    assert abs(lp.gauge_lp(A, b) - 0.25) < 1e-7  # z = (0.25, 0.25, 0.25)
    assert calls == ["highs", "highs-ipm"]
