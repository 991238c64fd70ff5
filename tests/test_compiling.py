"""What the compiled paths share (``torchrl_brsl._compiling``): code objects per owner, inductor's options for small
tensors."""
import types

import pytest
import torch
from torch._higher_order_ops.while_loop import while_loop

from torchrl_brsl import _compiling
from torchrl_brsl._compiling import inductor_kwargs, own_code, small_matmul, vector_options


class _Isa:
    def __init__(self, width):
        self.width = width

    def bit_width(self):
        return self.width


@pytest.fixture
def isa(monkeypatch):
    """Set the vector width inductor would pick (``None``: picking it fails); the cache is cleared around it."""
    import torch._inductor.cpu_vec_isa as cpu_vec_isa

    def use(width):
        def pick():
            if width is None:
                raise RuntimeError("no C++ compiler")
            return _Isa(width)
        monkeypatch.setattr(cpu_vec_isa, "pick_vec_isa", pick)
        vector_options.cache_clear()
    yield use
    vector_options.cache_clear()


@pytest.mark.parametrize("width, options", [(512, {"cpp.simdlen": 256}), (256, {}), (128, {}), (None, {})])
def test_vectors_narrow_only_where_inductor_would_use_avx512(isa, width, options):
    isa(width)
    assert vector_options() == options


def test_the_callers_own_choices_are_kept(isa):
    isa(512)
    assert inductor_kwargs({"backend": "aot_eager"}, cpp_wrapper=True) == {"backend": "aot_eager"}
    assert inductor_kwargs({"mode": "max-autotune"}) == {"mode": "max-autotune"}
    assert inductor_kwargs({"options": {"cpp_wrapper": False}}, cpp_wrapper=True) == {"options": {"cpp_wrapper": False}}
    assert inductor_kwargs({"dynamic": True}, cpp_wrapper=True) == {
        "dynamic": True, "options": {"cpp.simdlen": 256, **_compiling.CACHEABLE_LOOPS, "cpp_wrapper": True}}
    isa(256)
    assert inductor_kwargs({}) == {"options": _compiling.CACHEABLE_LOOPS}


def test_the_options_are_inductors():
    """The option names exist in this torch's inductor config (a rename would otherwise fail only at compile)."""
    with torch._inductor.config.patch({"cpp.simdlen": 256, "cpp_wrapper": True, **_compiling.CACHEABLE_LOOPS}):
        assert torch._inductor.config.cpp.simdlen == 256
    assert _compiling.vector_options() in ({}, {"cpp.simdlen": 256})


def test_copies_of_a_function_do_not_share_automatic_dynamic_shapes():
    """A copy compiled for other sizes than an earlier copy's keeps its sizes static: the compiler's automatic
    dynamic shapes, keyed by file, line and name, once made a second model's plan graphs symbolic (3x slower)."""
    def double(x):
        return x * 2

    symbolic = []

    def backend(graph, example_inputs):
        symbolic.append(any(isinstance(node.meta.get("example_value"), torch.SymInt)
                            for node in graph.graph.nodes if node.op == "placeholder"))
        return graph

    for size in (3, 5):
        torch.compile(own_code(double), backend=backend)(torch.ones(size))
    assert symbolic == [False, False]


@pytest.mark.parametrize("transpose_b", [False, True])
def test_small_matmul_compiled_in_a_loop_equals_the_product(transpose_b):
    """Compiled, the product is summed by hand, also inside a ``while_loop`` body that uses a captured operand
    twice (as the step uses a leaf's slopes: there ``b.mT`` and ``b`` would enter the loop as aliased inputs, which
    it refuses); eagerly it is ``a @ b``."""
    gen = torch.Generator().manual_seed(0)
    a = torch.randn(3, 4, 2, 5, dtype=torch.float64, generator=gen)
    b = torch.randn(4, 6, 5, dtype=torch.float64, generator=gen)
    holder = types.SimpleNamespace(operand=b if transpose_b else b.mT.contiguous())  # [4, 6, 5] or [4, 5, 6]
    expected = a @ b.mT * b.sum()  # [3, 4, 2, 6]

    def loop(x):
        def body(i, x):
            return i + 1, small_matmul(a, holder.operand, transpose_b=transpose_b) * holder.operand.sum() + 0 * x
        return while_loop(lambda i, x: i < 2, body, (torch.zeros((), dtype=torch.long), x))[1]

    torch.testing.assert_close(small_matmul(a, holder.operand, transpose_b=transpose_b) * b.sum(), expected)
    compiled = torch.compile(loop, backend="aot_eager", fullgraph=True)(torch.zeros_like(expected))
    torch.testing.assert_close(compiled, expected)


def test_plain_layout_gives_one_kind_of_input_to_a_compiled_graph():
    """A row cut from an expanded tensor and detached keeps stride 0 on its dim of size 1 (``contiguous()`` keeps
    it, and the graph's guards see it): a second graph without ``plain_layout`` (the teeth), none with it. Inputs
    already plain are passed through, not copied."""
    from torch._dynamo.utils import counters

    row = torch.ones(1, 3).expand(4, 3)[1:2].detach()
    assert row.stride() == (0, 1) and row.contiguous().stride() == (0, 1)
    plain = _compiling.plain_layout(row)
    assert plain.stride() == (3, 1) and torch.equal(plain, row)
    fresh = torch.ones(1, 3)
    assert _compiling.plain_layout(fresh) is fresh
    view = torch.ones(2, 3)[:1]
    assert _compiling.plain_layout(view)._base is None

    def double(x):
        return x * 2

    for prepare, graphs in ((lambda t: t, 2), (_compiling.plain_layout, 1)):
        compiled, frames = torch.compile(own_code(double), backend="eager"), counters["frames"]["ok"]
        compiled(prepare(torch.ones(1, 3)))
        compiled(prepare(row))
        assert counters["frames"]["ok"] - frames == graphs


_CACHED_RUNS = """
import json, sys
import torch
from torch._dynamo.utils import counters
from torch._higher_order_ops.while_loop import while_loop
from torchrl_brsl._compiling import own_code

def adding_loop(increment):
    def loop(x):
        return while_loop(lambda i, x: i < 3, lambda i, x: (i + 1, x + increment),
                          (torch.zeros((), dtype=torch.long), x))[1]
    return own_code(loop)

runs = []
for options, increment in json.loads(sys.argv[1]):
    torch._dynamo.reset()  # as in a new process
    hits = counters["inductor"]["fxgraph_cache_hit"]
    result = torch.compile(adding_loop(increment), options=options)(torch.zeros(2, dtype=torch.float64))
    runs.append([result.tolist(), counters["inductor"]["fxgraph_cache_hit"] == hits + 1])
print(json.dumps(runs))
"""


@pytest.fixture(scope="module")
def cached_runs(tmp_path_factory) -> dict[str, list[tuple[list[float], bool]]]:
    """Loops adding a constant three times, compiled in turn in a fresh process with an empty on-disk cache of
    inductor's, each after the compiler's reset (as in a new process): per series of ``(options, increment)``, their
    results and whether each graph came from the cache."""
    import json
    import os
    import subprocess
    import sys

    series = {"plain": [({}, 1.0)] * 2, "marked": [(_compiling.CACHEABLE_LOOPS, 1.0)] * 2,
              "package": [(inductor_kwargs({})["options"], increment) for increment in (0.5, 1.5, 0.5)]}
    env = {**os.environ, "TORCHINDUCTOR_CACHE_DIR": str(tmp_path_factory.mktemp("inductor"))}
    done = subprocess.run([sys.executable, "-c", _CACHED_RUNS, json.dumps(sum(series.values(), []))],
                          capture_output=True, text=True, env=env, check=True, timeout=600)
    runs = iter(tuple(run) for run in json.loads(done.stdout.strip().splitlines()[-1]))
    return {name: [next(runs) for _ in steps] for name, steps in series.items()}


@pytest.mark.parametrize("series, cached", [("plain", False), ("marked", True)])
def test_a_loops_graph_is_cached_with_the_option(cached_runs, series, cached):
    """Compiled again, a graph holding a ``while_loop`` comes from inductor's cache with :data:`CACHEABLE_LOOPS` and
    is compiled again without it (the option's teeth)."""
    assert cached_runs[series] == [([3.0, 3.0], False), ([3.0, 3.0], cached)]


def test_cached_loops_that_differ_only_in_their_body_keep_their_own_graphs(cached_runs):
    """The cache's key holds the loop's body: a loop adding 1.5 is not served the graph of one adding 0.5, which the
    cache holds (it serves that one again), with this package's options."""
    assert cached_runs["package"] == [([1.5, 1.5], False), ([4.5, 4.5], False), ([1.5, 1.5], True)]


def test_quick_tracing_turns_the_fake_tensor_cache_off_for_its_call_only():
    """The warm-ups' setting (``quick_tracing``) holds inside the call and is restored after it, an error included."""
    def fails():
        assert not torch._dynamo.config.fake_tensor_cache_enabled
        raise KeyError("inside")

    assert torch._dynamo.config.fake_tensor_cache_enabled  # dynamo's default
    assert _compiling.quick_tracing(lambda: torch._dynamo.config.fake_tensor_cache_enabled)() is False
    with pytest.raises(KeyError, match="inside"):
        _compiling.quick_tracing(fails)()
    assert torch._dynamo.config.fake_tensor_cache_enabled
