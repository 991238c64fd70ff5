"""What the compiled paths share: functions with code objects of their own, inductor's options for small
tensors, and a warning when compiling fails."""
from __future__ import annotations

import functools
import itertools
import types
import warnings
from typing import Callable

import torch
from torch import Tensor


_COPIES = itertools.count(1)


def own_code(function: Callable) -> types.FunctionType:
    """A copy of ``function`` with a code object of its own, named ``<name>_<n>`` (``n`` counts the copies).

    :func:`torch.compile` keys its graphs (and its limit on recompilations) by code object, so a
    copy per owner and use keeps that owner's graphs apart from every other's. Its automatic dynamic
    shapes are keyed by the code's file, line and name instead: with the name shared, a second model's
    tensors of other sizes made every later model's graphs symbolic in them: its plan ran 3x slower at
    batch 1 and 8x at batch 16 (``benchmarks/bench_compiled_step.py`` compiles several models in one process).

    Examples:
        >>> def f(x):
        ...     return x
        >>> own_code(f).__code__.co_name != own_code(f).__code__.co_name
        True
    """
    code = function.__code__.replace(co_name=f"{function.__code__.co_name}_{next(_COPIES)}")
    return types.FunctionType(code, function.__globals__, function.__name__, function.__defaults__,
                              function.__closure__)


def small_matmul(a: Tensor, b: Tensor, transpose_b: bool = False) -> Tensor:
    """``a @ b`` (``a @ b.mT`` with ``transpose_b``) of small operands, ``[..., i, k]`` and ``[..., k, j]``
    (``[..., j, k]``), broadcast.

    Inside a compiled graph, a product summed by hand, which inductor fuses into the kernels around it; a
    matrix product would be a BLAS call with a buffer of its own at every use, and in a traced loop
    ``b.mT`` of a captured tensor would alias it (which ``while_loop`` refuses).

    Examples:
        >>> a, b = torch.randn(3, 2, 4), torch.randn(4, 5)
        >>> torch.allclose(small_matmul(a, b), a @ b)
        True
    """
    if torch.compiler.is_compiling():
        if transpose_b:
            return (a.unsqueeze(-2) * b.unsqueeze(-3)).sum(-1)
        return (a.unsqueeze(-1) * b.unsqueeze(-3)).sum(-2)
    return a @ (b.mT if transpose_b else b)


def plain_layout(tensor: Tensor) -> Tensor:
    """``tensor`` itself, or a copy, with the strides of a new contiguous tensor and no base: the one kind of input a
    compiled graph's guards accept without recompiling. A view's guards read its base, and a dim of size 1 may carry
    any stride, which ``contiguous()`` keeps (0 after ``expand``, also once ``detach()`` has dropped the base).

    Examples:
        >>> row = torch.ones(1, 2).expand(4, 2)[1:2].detach()
        >>> row.stride(), plain_layout(row).stride()
        ((0, 1), (2, 1))
    """
    expected, size = [], 1
    for length in reversed(tensor.shape):
        expected.append(size)
        size *= length
    if tensor._base is None and tensor.stride() == tuple(reversed(expected)):
        return tensor
    return tensor.clone(memory_format=torch.contiguous_format)


def quick_tracing(function: Callable) -> Callable:
    """``function`` run with dynamo tracing without its fake-tensor cache: for the warm-ups that compile this package's
    graphs.

    With the graphs' sizes symbolic, each cache entry is checked by building the operation's output a second time,
    symbolically, and the loops' operations rarely repeat with the same arguments, so the cache cost more than it
    saved: compiling the Turtlebot's body-frame model and appending its layer (its checks and the facet QP, inductor's
    cache warm) took 26-28 s without it against 37-40 s with it, one CPU core. The graphs are the same (the cache only
    memoises the tracing's fake outputs); a graph that compiles later, outside a warm-up, traces with dynamo's default.

    Examples:
        >>> quick_tracing(lambda: torch._dynamo.config.fake_tensor_cache_enabled)()
        False
    """
    @functools.wraps(function)
    def traced(*args, **kwargs):
        with torch._dynamo.config.patch(fake_tensor_cache_enabled=False):
            return function(*args, **kwargs)
    return traced


def warn_fallback(what: str, error: Exception, instead: str = "eagerly") -> None:
    """Say why a compiled path failed (the error's last line); its caller runs it ``instead`` from then on.

    The warning points at the caller of the function that calls this one.
    """
    reason = (str(error).strip().splitlines() or [""])[-1]
    warnings.warn(f"{what} failed ({type(error).__name__}: {reason}); running it {instead} from now on",
                  RuntimeWarning, stacklevel=3)


def inductor_kwargs(compile_kwargs: dict, **options) -> dict:
    """:func:`torch.compile` arguments with inductor's ``options`` for this package's graphs, where the caller
    left inductor's options to us (inductor the backend, no ``options`` or ``mode`` of their own).

    The graphs hold many small tensors (dims of 2 to 30): inductor's C++ code vectorises their
    innermost loops, and on an AVX-512 CPU a vector of 16 doubles is mostly masked lanes. Vectors
    of 256 bits (:func:`vector_options`) ran a 6-D model's plan loop 1.3x faster at batch 1 and
    1.9x at batches 16 and 64, with the same sets to rounding (``benchmarks/bench_compiled_step.py
    --vectors``). Graphs with a ``while_loop`` (a plan's loop) go to inductor's on-disk cache too
    (:data:`CACHEABLE_LOOPS`).

    Examples:
        >>> inductor_kwargs({}, cpp_wrapper=True)["options"]["cpp_wrapper"]
        True
        >>> inductor_kwargs({"backend": "aot_eager"})
        {'backend': 'aot_eager'}
    """
    if compile_kwargs.get("backend", "inductor") != "inductor" or "options" in compile_kwargs \
            or "mode" in compile_kwargs:
        return dict(compile_kwargs)
    return {**compile_kwargs, "options": {**vector_options(), **CACHEABLE_LOOPS, **options}}


CACHEABLE_LOOPS = {"unsafe_marked_cacheable_functions": {"torch.ops.higher_order.while_loop": torch.__version__}}
"""Inductor's option that lets its caches (compiled graphs, AOT autograd) keep graphs holding a ``while_loop``.

Inductor (torch 2.13) leaves them out by default, so every process traced a plan's loop and generated and compiled its
C++ code again. With them cached, a fresh process on one CPU core took 19-20 s instead of 25-33 s in
:meth:`~torchrl_brsl.reach.DataDrivenReach.compile_steps` of the bicycle's local model, and 29 s instead of 48-55 s to
compile the Turtlebot's body-frame model and append the layer (its checks and the facet QP), the cache warm from an
earlier process. The cache's key holds the loop's condition and body graphs (a graph module is hashed with its
submodules' code) and the constants a graph holds, so a cached loop is one traced from the same operations on the same
shapes and constants (``tests/test_compiling.py`` compiles two loops that differ only in their body's constant). The
option's name says "unsafe" because torch has not vetted the operator for caching; the key's completeness is what that
rests on.
"""


@functools.cache
def vector_options() -> dict:
    """``{"cpp.simdlen": 256}`` where inductor would vectorise wider (AVX-512), else ``{}`` (its choice)."""
    try:
        from torch._inductor.cpu_vec_isa import pick_vec_isa

        width = pick_vec_isa().bit_width()
    except Exception:  # no C++ compiler or an unknown CPU: inductor decides (and warns) itself
        return {}
    return {"cpp.simdlen": 256} if width > 256 else {}
