"""The ``Examples:`` sections of the baselines' docstrings run and print what they claim."""
import doctest
import importlib

import pytest

MODULES = ["torchrl_brsl.baselines._common", "torchrl_brsl.baselines.secas", "torchrl_brsl.baselines.sailr",
           "torchrl_brsl.baselines.rts"]


@pytest.mark.parametrize("name", MODULES)
def test_docstring_examples(name):
    module = importlib.import_module(name)
    result = doctest.testmod(module, optionflags=doctest.ELLIPSIS | doctest.NORMALIZE_WHITESPACE)
    assert result.attempted > 0 and result.failed == 0
