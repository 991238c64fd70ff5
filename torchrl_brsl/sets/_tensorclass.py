"""``tensorclass`` that keeps the class docstring (the decorator replaces it by the signature)."""
from __future__ import annotations

from tensordict import tensorclass


def documented_tensorclass(cls):
    """Apply :func:`tensordict.tensorclass` and restore ``cls.__doc__``."""
    doc = cls.__doc__
    cls = tensorclass(cls)
    if doc:
        cls.__doc__ = doc
    return cls
