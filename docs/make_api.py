"""Write ``docs/api.md``: the public API of every package, from its docstrings.

Usage: ``python docs/make_api.py`` (``--check`` exits 1 if the file is out of date).
"""
from __future__ import annotations

import argparse
import importlib
import inspect
import sys
from pathlib import Path

PACKAGES = ["torchrl_brsl.sets", "torchrl_brsl.reach", "torchrl_brsl.collision", "torchrl_brsl.safety",
            "torchrl_brsl.models", "torchrl_brsl.planning", "torchrl_brsl.modules", "torchrl_brsl.baselines", "envs"]
OUT = Path(__file__).with_name("api.md")


def _signature(obj) -> str:
    try:
        return str(inspect.signature(obj))
    except (TypeError, ValueError):
        return ""


def _entry(name: str, obj) -> list[str]:
    kind = "class" if inspect.isclass(obj) else "function" if callable(obj) else "constant"
    head = f"### `{name}{_signature(obj) if kind != 'constant' else ''}`"
    doc = inspect.getdoc(obj) if kind != "constant" else None
    lines = [head, ""]
    if doc:
        lines += [doc.split("\n\n")[0].strip(), ""]
    if kind == "class":
        for attr, member in sorted(vars(obj).items()):
            if attr.startswith("_") or not (inspect.isfunction(member) or isinstance(member, (classmethod, property))):
                continue
            target = member.__func__ if isinstance(member, classmethod) else member
            target = target.fget if isinstance(target, property) else target
            if getattr(target, "__qualname__", "").split(".")[0] != obj.__name__:
                continue  # inherited or generated (e.g. tensorclass methods)
            summary = (inspect.getdoc(target) or "").split("\n\n")[0].replace("\n", " ").strip()
            sig = "" if isinstance(member, property) else _signature(target)
            lines.append(f"- `{attr}{sig}`" + (f": {summary}" if summary else ""))
        lines.append("")
    return lines


def render() -> str:
    lines = ["# API reference", "", "Generated from the docstrings by `python docs/make_api.py`; the "
             "docstrings hold the shapes and examples.", ""]
    for package in PACKAGES:
        module = importlib.import_module(package)
        lines += [f"## `{package}`", "", (inspect.getdoc(module) or "").strip(), ""]
        for name in sorted(getattr(module, "__all__", [])):
            lines += _entry(name, getattr(module, name))
    return "\n".join(lines).rstrip() + "\n"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--check", action="store_true", help="fail if docs/api.md is out of date")
    args = parser.parse_args()
    text = render()
    if args.check:
        sys.exit(0 if OUT.exists() and OUT.read_text() == text else 1)
    OUT.write_text(text)
    print(f"wrote {OUT}")


if __name__ == "__main__":
    main()
