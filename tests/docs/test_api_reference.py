"""Every public name of every package has its autodoc entry in the API reference pages.

Reads the sources of ``docs/api/*.rst`` (no Sphinx build): a name counts when an
``autoclass``/``autofunction``/``autodata``/... directive names it under its package's
``currentmodule``, or by its full dotted path.
"""
import importlib
import re
from pathlib import Path

import pytest

API = Path(__file__).resolve().parents[2] / "docs" / "api"
PACKAGES = ["torchrl_brsl.sets", "torchrl_brsl.reach", "torchrl_brsl.collision", "torchrl_brsl.safety",
            "torchrl_brsl.models", "torchrl_brsl.planning", "torchrl_brsl.modules", "torchrl_brsl.baselines", "envs"]
DIRECTIVE = re.compile(r"^\s*\.\. (?:py:)?(currentmodule|module|automodule|auto\w+)::\s*(\S+)", re.M)


def documented_names() -> dict[str, set[str]]:
    """``{module: {names}}`` of the autodoc directives in the API pages."""
    names: dict[str, set[str]] = {}
    for page in sorted(API.glob("*.rst")):
        module = None
        for kind, target in DIRECTIVE.findall(page.read_text()):
            if kind in ("currentmodule", "module", "automodule"):
                module = target
                continue
            if kind == "automodule":
                continue
            if module is not None and not any(target.startswith(p + ".") for p in PACKAGES):
                target = f"{module}.{target}"
            owner, _, name = target.rpartition(".")
            names.setdefault(owner, set()).add(name)
    return names


def test_every_package_has_a_page_in_the_api_index():
    index = (API / "index.rst").read_text()
    for package in PACKAGES:
        page = package.split(".")[-1]
        assert (API / f"{page}.rst").exists(), f"docs/api/{page}.rst is missing"
        assert re.search(rf"^\s+{page}\s*$", index, re.M), f"docs/api/index.rst does not list {page}"


@pytest.mark.parametrize("package", PACKAGES)
def test_every_public_name_is_in_an_autodoc_directive(package):
    public = set(importlib.import_module(package).__all__)
    documented = documented_names().get(package, set())
    missing = sorted(public - documented)
    assert not missing, f"add to docs/api/{package.split('.')[-1]}.rst: " + ", ".join(missing)
    stale = sorted(documented - public)
    assert not stale, f"not in {package}.__all__ any more, remove from docs/api: " + ", ".join(stale)
