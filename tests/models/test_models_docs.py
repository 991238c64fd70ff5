"""The ``Examples:`` sections of the ``models`` docstrings run and print what they claim."""
import doctest
import importlib

import pytest

MODULES = ["torchrl_brsl.models.ensemble", "torchrl_brsl.models.loss", "torchrl_brsl.models.normalizer"]


@pytest.mark.parametrize("name", MODULES)
def test_docstring_examples(name):
    module = importlib.import_module(name)
    result = doctest.testmod(module, optionflags=doctest.ELLIPSIS | doctest.NORMALIZE_WHITESPACE)
    assert result.attempted > 0 and result.failed == 0
