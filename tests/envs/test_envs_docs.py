"""The ``Examples:`` sections of the ``envs`` docstrings run and print what they claim."""
import doctest
import importlib

import pytest

MODULES = [
    "envs._aerial",
    "envs._lidar",
    "envs._obstacles",
    "envs._registry",
    "envs._rotor",
    "envs._safety_info",
    "envs._task",
    "envs._wrapper",
    "envs.diffdrive_nav",
    "envs.hexarotor_wind",
    "envs.plotting",
    "envs.point_boxes",
    "envs.point_circle",
    "envs.quadrotor_nav",
]


@pytest.mark.parametrize("name", MODULES)
def test_docstring_examples(name):
    module = importlib.import_module(name)
    result = doctest.testmod(module, optionflags=doctest.ELLIPSIS | doctest.NORMALIZE_WHITESPACE)
    assert result.failed == 0
