"""What the compiled paths share: functions with code objects of their own, and a warning when compiling fails."""
from __future__ import annotations

import types
import warnings
from typing import Callable


def own_code(function: Callable) -> types.FunctionType:
    """A copy of ``function`` with a code object of its own.

    :func:`torch.compile` keys its graphs (and its limit on recompilations) by code object, so a
    copy per owner and use keeps that owner's graphs apart from every other's.
    """
    return types.FunctionType(function.__code__.replace(), function.__globals__, function.__name__,
                              function.__defaults__, function.__closure__)


def warn_fallback(what: str, error: Exception, instead: str = "eagerly") -> None:
    """Say why a compiled path failed (the error's last line); its caller runs it ``instead`` from then on.

    The warning points at the caller of the function that calls this one.
    """
    reason = (str(error).strip().splitlines() or [""])[-1]
    warnings.warn(f"{what} failed ({type(error).__name__}: {reason}); running it {instead} from now on",
                  RuntimeWarning, stacklevel=3)
