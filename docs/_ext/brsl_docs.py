"""Sphinx helpers of this site.

* ``safety-info``: a table of a task's safety constants, read from :func:`envs.safety_info` at
  build time, so the task pages cannot drift from the code.
* API pages document what the project defines: members that a class only carries because a
  decorator (``tensorclass``) or a base class outside the project put them there are skipped.
"""
from __future__ import annotations

import inspect

from docutils import nodes
from docutils.parsers.rst import Directive

PROJECT_MODULES = ("torchrl_brsl", "envs", "recipes")


def _fmt(value) -> str:
    if hasattr(value, "tolist"):
        value = value.tolist()
    if isinstance(value, float):
        return f"{value:g}"
    if isinstance(value, (list, tuple)):
        return "(" + ", ".join(_fmt(v) for v in value) + ("," if len(value) == 1 else "") + ")"
    return str(value)


def safety_rows(task: str) -> list[tuple[str, str, str]]:
    """``(field, value, meaning)`` rows of ``envs.safety_info(task)``."""
    import envs

    info = envs.safety_info(task)
    half_widths = info.noise_generators.abs().sum(-1)
    noisy = [f"{i}: ±{_fmt(float(w))}" for i, w in enumerate(half_widths) if w > 0]
    return [
        ("state_dim / action_dim", f"{info.state_dim} / {info.action_dim}", "sizes of the state and action entries"),
        ("position_dims", _fmt(info.position_dims), "positions in the state (translation invariant)"),
        ("velocity_dims", _fmt(info.velocity_dims), "zero once the robot is stopped"),
        ("heading_dims", _fmt(info.heading_dims) if info.heading_dims else "none",
         "heading of a yaw-invariant robot (body-frame fit)"),
        ("obstacle_dim", str(info.obstacle_dim), "dimension of the obstacle zonotopes"),
        ("action_low / action_high", f"{_fmt(info.action_low)} / {_fmt(info.action_high)}", "action bounds"),
        ("noise W", ", ".join(noisy) + (f" (centre {_fmt(info.noise_center)})" if info.noise_center.any() else ""),
         "half-widths of the noise box per state dim (others 0)"),
        ("n_brk", str(info.n_brk), "steps within which the braking policy stops the robot"),
        ("n_plan", str(info.n_plan), "the paper's plan length with this n_brk"),
        ("braking_action", _fmt(info.braking_action), "holds a stopped robot stopped (Assumption 1)"),
        ("stop_tolerance", _fmt(info.stop_tolerance), "largest |velocity| that counts as stopped"),
        ("dt", f"{_fmt(info.dt)} s", "control period"),
    ]


class SafetyInfoDirective(Directive):
    """``.. safety-info:: TASK``: the task's :class:`envs.SafetyInfo` as a table."""

    required_arguments = 1
    has_content = False

    def run(self):
        rows = safety_rows(self.arguments[0])
        table = nodes.table(classes=["safety-info"])
        group = nodes.tgroup(cols=3)
        table += group
        for width in (22, 30, 48):
            group += nodes.colspec(colwidth=width)
        head = nodes.thead()
        group += head
        head += self._row(("field", "value", "meaning"), literal=False)
        body = nodes.tbody()
        group += body
        for row in rows:
            body += self._row(row, literal=True)
        return [table]

    @staticmethod
    def _row(cells, literal: bool):
        row = nodes.row()
        for i, text in enumerate(cells):
            entry = nodes.entry()
            paragraph = nodes.paragraph()
            paragraph += nodes.literal(text, text) if literal and i < 2 else nodes.Text(text)
            entry += paragraph
            row += entry
        return row


def _defined_here(obj) -> bool | None:
    """Whether a class member comes from the project (``None``: cannot tell, keep autodoc's choice)."""
    target = obj
    if isinstance(target, (classmethod, staticmethod)):
        target = target.__func__
    if isinstance(target, property):
        target = target.fget
    if not (inspect.isfunction(target) or inspect.ismethod(target) or inspect.isroutine(target)):
        return None
    module = getattr(target, "__module__", None) or ""
    return module.split(".")[0] in PROJECT_MODULES


def skip_foreign_members(app, what, name, obj, skip, options):
    if what == "class" and _defined_here(obj) is False:
        return True
    if what == "class" and type(obj).__name__ == "_tuplegetter":
        return True  # a NamedTuple field: its class docstring's Attributes section describes it
    return None


def drop_type_docstrings(app, what, name, obj, options, lines):
    """A constant without a doc comment shows its value, not the docstring of its type (``dict``)."""
    if what == "data" and lines and inspect.getdoc(type(obj)) and "\n".join(lines).strip() == inspect.getdoc(type(obj)).strip():
        lines.clear()


def setup(app):
    app.add_directive("safety-info", SafetyInfoDirective)
    app.connect("autodoc-skip-member", skip_foreign_members)
    app.connect("autodoc-process-docstring", drop_type_docstrings)
    return {"version": "1", "parallel_read_safe": True, "parallel_write_safe": True}
