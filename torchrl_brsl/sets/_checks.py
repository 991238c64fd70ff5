"""Input validation shared by the set classes: errors name the offending argument."""
from __future__ import annotations

import contextlib

import torch
from torch import Tensor

_VALUE_CHECKS = [True]


@contextlib.contextmanager
def skip_value_checks():
    """Within this context, sets are built without the NaN/inf scan of their tensors.

    For library code that builds sets from already validated tensors on a hot path (the scan
    synchronises with the device); shape and dtype checks still run.
    """
    _VALUE_CHECKS.append(False)
    try:
        yield
    finally:
        _VALUE_CHECKS.pop()


def value_checks_enabled() -> bool:
    """Whether sets and checks scan their tensors for NaN/inf (off within :func:`skip_value_checks`)."""
    return _VALUE_CHECKS[-1]


def check_tensor(name: str, value, *, min_ndim: int = 0, finite: bool = True) -> Tensor:
    """Return ``value`` as a floating tensor or raise a ``ValueError`` naming ``name``.

    Args:
        name: the argument name used in error messages.
        value: a tensor (or anything ``torch.as_tensor`` accepts).
        min_ndim: the least number of dimensions ``value`` must have.
        finite: reject NaN and infinite entries.
    """
    if not isinstance(value, Tensor):
        try:
            value = torch.as_tensor(value, dtype=torch.get_default_dtype())
        except (TypeError, ValueError, RuntimeError) as err:
            raise ValueError(f"`{name}` must be a tensor, got {type(value).__name__}") from err
    if not value.is_floating_point():
        raise ValueError(f"`{name}` must have a floating dtype, got {value.dtype}")
    if value.ndim < min_ndim:
        raise ValueError(f"`{name}` must have at least {min_ndim} dimension(s), got shape {tuple(value.shape)}")
    if finite and _VALUE_CHECKS[-1] and not bool(torch.isfinite(value.detach()).all()):
        raise ValueError(f"`{name}` contains NaN or infinite entries")
    return value


def check_same_dtype_device(**tensors: Tensor) -> None:
    """Raise a ``ValueError`` if the given tensors differ in dtype or device."""
    items = list(tensors.items())
    first_name, first = items[0]
    for name, tensor in items[1:]:
        if tensor.dtype != first.dtype:
            raise ValueError(f"`{name}` has dtype {tensor.dtype} but `{first_name}` has {first.dtype}")
        if tensor.device != first.device:
            raise ValueError(f"`{name}` is on {tensor.device} but `{first_name}` is on {first.device}")


def broadcast_shapes(*shapes) -> torch.Size:
    """:func:`torch.broadcast_shapes`, without its cost (6.7 µs against 0.8) where the shapes are equal already (the
    usual case on a control loop's hot path).

    Examples:
        >>> broadcast_shapes(torch.Size([3]), (3,)), broadcast_shapes((2, 1), (3,))
        (torch.Size([3]), torch.Size([2, 3]))
    """
    first = torch.Size(shapes[0])
    if all(first == tuple(shape) for shape in shapes[1:]):
        return first
    return torch.broadcast_shapes(*shapes)


def broadcast_batch(name: str, shape, batch) -> torch.Size:
    """Broadcast the batch shape of argument ``name`` with a set's ``batch``, or raise ``ValueError``."""
    try:
        return torch.broadcast_shapes(torch.Size(shape), torch.Size(batch))
    except RuntimeError as err:
        raise ValueError(
            f"`{name}` has batch shape {tuple(shape)}, which does not broadcast with the set's batch shape {tuple(batch)}"
        ) from err


def check_last_dim(name: str, value: Tensor, n: int) -> None:
    """Raise ``ValueError`` unless ``value`` is ``[..., n]``."""
    if value.ndim < 1 or value.shape[-1] != n:
        raise ValueError(f"`{name}` must have last dimension {n}, got shape {tuple(value.shape)}")


def check_dims(name: str, dims, n: int) -> list[int]:
    """Validate a list of dimension indices into an ``n``-dimensional space."""
    dims = [int(d) for d in dims]
    if not dims:
        raise ValueError(f"`{name}` must name at least one dimension")
    if any(d < -n or d >= n for d in dims):
        raise ValueError(f"`{name}`={dims} out of range for a {n}-dimensional set")
    return [d % n for d in dims]


def default_tol(dtype: torch.dtype) -> float:
    """Containment tolerance on the gauge: 1e-9 in float64, 1e-5 in lower precision."""
    return 1e-9 if dtype == torch.float64 else 1e-5
