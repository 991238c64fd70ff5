"""One step of the local (leaf-wise) model on zonotopes: the hot path of plan-dependent reachability.

A step ``R_j -> R_{j+1}`` under an action (:class:`LocalStep`) reads the set's ranges along
every direction the model uses (the leaves' split directions, each output's hinges and
product factors), relaxes the hinges and products over them, picks per output the leaf
holding the set's centre with the worst error over the leaves the set meets
(:func:`~torchrl_brsl.reach.cells.leaf_bounds`), folds the relaxations into that leaf's
affine model and maps the set. A body-frame model then turns its rotated pairs into the world
frame (:meth:`BodyFrame.rotate`); the noise comes last.

Every quantity that depends only on the fitted model (the directions stacked in state units,
the leaves' rows, the placements of the rotated pairs) is built once, so a step is a fixed,
short sequence of batched tensor operations: its cost at batch 1 is the operations' count
(about 300 in eager mode, 0.5-3 ms). Compiled (``compile_kwargs``, :func:`torch.compile`), the
same operations run as fused kernels, 2-4x faster at batch 1 to 16; a whole plan without
gradients (:meth:`LocalStep.plan_sets`, the checking path) runs as one compiled loop whose body is
a handful of fused kernels and two ``topk`` calls (the small matrix products summed by hand,
:func:`~torchrl_brsl._compiling.small_matmul`), about 15x faster than eager at batch 1
(``benchmarks/bench_reach.py``).
"""
from __future__ import annotations

import types
from typing import Callable, Sequence

import torch
from torch import Tensor
from torch._higher_order_ops.while_loop import while_loop

from torchrl_brsl._compiling import inductor_kwargs, own_code, plain_layout, small_matmul, warn_fallback
from torchrl_brsl.reach.cells import NEAR_LEAVES, leaf_bounds, leaf_distance, leaf_gaps, leaf_layout
from torchrl_brsl.reach.hinges import product_relaxation, relu_relaxation
from torchrl_brsl.sets import Zonotope, pad_generators, reduce_girard
from torchrl_brsl.sets._checks import broadcast_shapes, skip_value_checks
from torchrl_brsl.sets.reduction import girard_columns


class LocalStep:
    """The step of a fitted local :class:`~torchrl_brsl.reach.DataDrivenReach` (``method="local"``).

    Built by the model (``model.step_sets`` calls it); holds views of the model's buffers and
    what is derived from them, on the model's device and dtype.

    Args:
        model: a fitted local model.
        compile_kwargs: arguments of :func:`torch.compile` to run the step compiled (``None``: eager).
            The first calls compile it (under a minute per graph with an empty cache, seconds with
            inductor's on-disk cache warm, the plan's loops too);
            the batch and the plan's length are symbolic and the generator width fixed at
            ``max_generators``, so every later shape reuses the graph. If compilation fails (e.g.
            no C++ compiler), a warning says why and the step runs eagerly from then on.
        step_functions: the model's copies of the step and the plan's loop to compile
            (:meth:`compiled_functions`; new ones if ``None``).

    Examples:
        >>> step = LocalStep(reach)
        >>> center, generators, covered = step(x0, torch.zeros(6, 0, dtype=torch.float64), u0)
    """

    def __init__(self, model, compile_kwargs: dict | None = None, step_functions: tuple | None = None):
        cells, scale = model._cells, model.input_scale
        like = dict(dtype=scale.dtype, device=scale.device)
        n, n_leaves, _ = cells.slopes.shape
        self.cells, self.state_dim, self.max_generators = cells, n, model.max_generators
        self.free = torch.tensor(model.free_dims, dtype=torch.long, device=scale.device)
        n_free = len(model.free_dims)
        self.inv_scale, self.inv_scale_free = 1 / scale, 1 / scale[:n_free]
        self.n_hinges, self.n_products = cells.hinge_knots.shape[-1], cells.product_knots.shape[-2]
        # every direction whose range over the set a step needs, in state and action units: [F, d]
        directions = torch.cat((cells.directions, cells.hinge_directions.flatten(0, 1),
                                cells.product_directions.flatten(0, 2))) / scale
        self.projection = directions.T.contiguous()
        self.projection_free = directions[:, :n_free].contiguous()
        self.knots = torch.cat((torch.zeros(cells.directions.shape[0], **like), cells.hinge_knots.flatten(),
                                cells.product_knots.flatten()))
        self.sizes = (cells.directions.shape[0], n * self.n_hinges, 2 * n * self.n_products)
        self.hinge_directions = cells.hinge_directions / scale  # [n, H, d]
        self.product_rows = cells.product_directions.flatten(1, 2) / scale  # [n, 2 Q, d], the factors' directions
        self.product_knots = cells.product_knots
        self.layout = leaf_layout(cells, model._weighted_data)
        self.near_leaves = min(NEAR_LEAVES, n_leaves)
        self.boxes = (cells.low.mT.contiguous(), cells.high.mT.contiguous())  # [n, f, M]
        self.slopes_by_input = cells.slopes.mT.clone(memory_format=torch.contiguous_format)  # [n, d + H + Q, M]
        self.leaf_rows = model._leaf_rows
        self.row_offset = torch.arange(n, device=scale.device) * n_leaves
        self.widths = (n, model.action_dim, 1, self.n_hinges, self.n_products)
        self.body_frame = model.body_frame
        self._noise(model)
        if self.body_frame is not None:
            self._rotation_tables(model)
        # per use: steps and whole plans (checking), each without tangents and with them (linearisation); plans also
        # with a `finish` (checking them in the same graph)
        self._compiled = self._compiled_loop = None
        self._brake_in_loop = self._finish_in_loop = True  # until a braking policy or a `finish` fails to compile
        if compile_kwargs is not None:
            step, tangent_step, loop, tangent_loop, *finished_loops = step_functions or LocalStep.compiled_functions()
            self._compiled = tuple(torch.compile(types.MethodType(f, self), **inductor_kwargs(compile_kwargs))
                                   for f in (step, tangent_step))
            if loop is not None:  # inductor's C++ wrapper: a loop of about 50 small kernels per step runs 2-3x
                # faster when its body is called from C++ rather than Python
                loop_kwargs = inductor_kwargs(compile_kwargs, cpp_wrapper=True)
                self._compiled_loop = tuple(torch.compile(types.MethodType(f, self), **loop_kwargs)
                                            for f in (loop, tangent_loop, *finished_loops))

    @staticmethod
    def compiled_functions(loop: bool = True) -> tuple:
        """Copies of :meth:`_step` (twice: without and with tangents) and of :meth:`_loop` (four times: without and
        with tangents, each without and with a ``finish``), each with a code object of its own, for a model to
        compile: the compiler keys its graphs (and its limit on recompilations) by code object, so copies per
        model and use keep that model's graphs when its step is rebuilt (after ``.to()``), never evict another
        model's, and keep each use's guards apart. Without ``loop``, ``None`` for the loop's copies (plans run as
        compiled steps)."""
        steps = tuple(own_code(f) for f in (LocalStep._step, LocalStep._step, *[LocalStep._loop] * 4))
        return steps if loop else steps[:2] + (None,) * 4

    def _noise(self, model) -> None:
        """The noise's columns: a box adds its radii to the error's diagonal, else its generators follow."""
        noise = model._diagonal_noise
        self.noise_generators = model.noise_generators if noise is None else None
        self.noise_radius = torch.zeros_like(model.noise_center) if noise is None else noise
        self.noise_center = model.noise_center

    def _rotation_tables(self, model) -> None:
        """The rotated dims pair by pair ``[2P]``, the placements of their blocks and boxes, their noise."""
        pairs = self.body_frame.rotated_pairs
        index = [d for pair in pairs for d in pair]
        like = dict(dtype=model.noise_center.dtype, device=model.noise_center.device)
        self.rotated = torch.tensor(index, dtype=torch.long, device=like["device"])
        self.moves = torch.tensor([float(pair == self.body_frame.position) for pair in pairs for _ in pair], **like)
        self.place = torch.zeros(self.state_dim, 2 * len(pairs), **like)  # dim of each rotated entry
        self.place[index, torch.arange(2 * len(pairs))] = 1.0
        # [P, n, 2]: where each pair's block goes, no alias (a traced loop)
        self.place_pairs = self.place.unflatten(-1, (len(pairs), 2)).permute(1, 0, 2).clone(
            memory_format=torch.contiguous_format)
        self.unrotated = torch.ones(self.state_dim, **like).index_fill(0, self.rotated, 0.0)
        self.box_noise = self.noise_radius[self.rotated]  # the rotated dims' noise goes to the box
        self.noise_radius = self.noise_radius * self.unrotated

    def __call__(self, center: Tensor, generators: Tensor, action: Tensor,
                 tangents: tuple[Tensor, Tensor] | None = None) -> tuple[Tensor, ...]:
        """``R_{j+1}`` of ``R_j = Z(center [..., n], generators [..., n, p])`` under ``action`` ``[..., m]``.

        Args:
            tangents: optional ``(dc [..., n, k], du [..., m, k])``: directions of the centre and
                the action, mapped to the new centre's to first order with the step's leaf
                models and relaxations held fixed (a linearisation for the adjusters).

        Returns:
            ``(center [..., n], generators [..., n, p'], covered [...])`` (generators reduced to
            ``max_generators`` when set); ``covered``: the step lies in the data's region. With
            ``tangents``, also the new centre's directions ``[..., n, k]``.
        """
        if self._compiled is not None and center.numel() > 0:
            try:
                return self._run_compiled(center, generators, action, tangents)
            except Exception as error:  # the compiler's failure must not stop a control loop
                warn_fallback("the compiled reachable-set step", error)
                self._compiled = None
        return self._step(center, generators, action, tangents)

    def plan_sets(self, center: Tensor, generators: Tensor, actions: Tensor,
                  tangents: tuple[Tensor, Tensor] | None = None,
                  brake: tuple[Callable[[Tensor], Tensor], int] | None = None,
                  finish: tuple[Callable[..., tuple[Tensor, ...]], tuple[Tensor, ...], tuple] | None = None) -> tuple:
        """The sets of whole plans: the steps under ``actions`` ``[..., P, m]`` from ``Z(center [..., n],
        generators [..., n, p])``.

        Compiled and without gradients, the plan runs as one graph (a ``while_loop`` over the step):
        about 3x faster than compiled steps and 8x faster than eager ones at batch 1
        (``benchmarks/bench_compiled_step.py``). Otherwise step by step.

        Args:
            tangents: optional ``(dc [..., n, k], du [..., P, m, k])``: directions of the initial centre
                and of every action, mapped along the plan as :meth:`__call__` maps them.
            brake: optional ``(policy, steps)``: after the plan, ``steps`` more steps under ``policy(centre)``
                (``[..., n] -> [..., m]``, the action the robot receives at each set's centre: a braking
                policy's tail), in the same loop when compiled (the policy must then be traceable, else
                the plan runs step by step). With ``tangents``, ``(policy, steps, policy_tangent)``:
                ``policy_tangent(centre [..., n], directions [..., n, k])`` gives the tail action's directions
                ``[..., m, k]`` (e.g. :meth:`~torchrl_brsl.safety.PlanChecker.brake_tangent`).
            finish: optional ``(function, batched, args)``: what is computed from the sets, in the plan's compiled
                loop when compiled (one graph, one call): ``function(centers [..., T, n], generators [..., T, n, p],
                covered [...], *batched, *args)``, traceable and batched over the leading dims (compiled, one flat
                batch dim); ``batched``: tensors with the plan's batch dims first, ``args``: constants. Its results
                ``[..., ...]`` replace ``(sets, covered)``; with ``tangents`` it also takes the centres' directions
                ``[..., T, n, k]`` (keyword ``directions``), and its results replace them too.

        Returns:
            ``(sets [..., T], covered [...])``: ``covered`` if every step is; with ``tangents``, also
            the centres' directions ``[..., T, n, k]``; with ``brake``, also (last) every step's action
            ``[..., T, m]`` (``T = P + steps``).
        """
        if brake is not None and tangents is not None and len(brake) < 3:
            raise ValueError("`brake` with `tangents` needs the policy's tangent map: (policy, steps, policy_tangent)")
        batch = broadcast_shapes(center.shape[:-1], generators.shape[:-2], actions.shape[:-2])
        inputs = (center, generators, actions, *(tangents or ()))
        differentiable = torch.is_grad_enabled() and any(t.requires_grad for t in inputs)
        loop = None
        if self._compiled_loop is not None and (finish is None or self._finish_in_loop):
            loop = self._compiled_loop[(tangents is not None) + 2 * (finish is not None)]
        if brake is not None and not self._brake_in_loop:
            loop = None
        steps = actions.shape[-2] + (brake[1] if brake else 0)
        if loop is not None and (steps < 2 or not batch.numel() or differentiable):
            loop = None
        if loop is None and finish is not None:  # the sets first, then what is computed from them
            sets, covered, *rest = self.plan_sets(center, generators, actions, tangents, brake)
            function, batched, args = finish
            along = {} if tangents is None else {"directions": rest.pop(0)}
            return (*function(sets.center, sets.generators, covered, *batched, *args, **along), *rest)
        if loop is not None:
            try:
                return self._run_compiled_loop(loop, batch, center, generators, actions, tangents, brake, finish)
            except Exception as error:  # the compiler's failure must not stop a control loop
                if finish is not None:  # e.g. a function the compiler cannot trace: the loop runs without it
                    warn_fallback("the compiled plan loop with a `finish`", error, instead="after the loop")
                    self._finish_in_loop = False
                    return self.plan_sets(center, generators, actions, tangents, brake, finish)
                if brake is not None:  # e.g. a policy the compiler cannot trace: plans without one keep the loop
                    warn_fallback("the compiled plan loop with a braking policy's tail", error, instead="step by step")
                    self._brake_in_loop = False
                else:
                    warn_fallback("the compiled reachable sets of a plan", error, instead="step by step")
                    self._compiled_loop = None
        covered = torch.ones(batch, dtype=torch.bool, device=center.device)
        centers, sets, moved, applied = [], [], [], []
        tangent, du = tangents if tangents is not None else (None, None)
        plan = actions.expand(*batch, *actions.shape[-2:]).unbind(-2)
        for j in range(steps):
            action = plan[j] if j < len(plan) else brake[0](center)
            if tangents is None:
                center, generators, inside = self(center, generators, action)
            else:
                action_tangent = du[..., j, :, :] if j < len(plan) else brake[2](center, tangent)
                center, generators, inside, tangent = self(center, generators, action, (tangent, action_tangent))
                moved.append(tangent)
            covered = covered & inside
            centers.append(center)
            sets.append(generators)
            applied.append(action)
        result = (stack_steps(centers, sets), covered)
        if tangents is not None:
            result += (torch.stack(moved, -3),)
        return result if brake is None else (*result, torch.stack(applied, -2))

    def _run_compiled_loop(self, loop, batch: torch.Size, center: Tensor, generators: Tensor, actions: Tensor,
                           tangents: tuple[Tensor, Tensor] | None,
                           brake: tuple[Callable[[Tensor], Tensor], int] | None, finish: tuple | None = None) -> tuple:
        """:meth:`plan_sets` through the compiled :meth:`_loop`, its inputs as :meth:`_compiled_inputs` makes them,
        steps first, and the plan's length (the tangents' count, the braking tail's length) dynamic: one graph
        for every length from 2 (and one more per braking policy). Without tangents, one plan is a graph of its
        own (``single``): padded to two, it cost what two plans do (the Turtlebot's 16-step plans: 1.30 against
        0.92 ms)."""
        count, n, width = batch.numel(), self.state_dim, self.max_generators
        single = count == 1 and tangents is None
        if tangents is not None:  # the action tangents travel with the actions: [..., T, m (1 + k)]
            du = tangents[1].expand(*batch, *tangents[1].shape[-3:])
            actions = torch.cat((actions.expand(*batch, *actions.shape[-2:]).unsqueeze(-1), du), dim=-1).flatten(-2)
        tail = ()
        if brake is not None:  # the policy, where its steps start, and placeholders for the actions it computes
            tail = (brake[0], torch.tensor(actions.shape[-2], device=center.device),
                    brake[2] if tangents is not None else None)
            actions = torch.cat((actions, actions.new_zeros(*actions.shape[:-2], brake[1], actions.shape[-1])), -2)
        horizon = actions.shape[-2]
        function, batched, args = finish if finish is not None else (None, (), ())
        center, generators, actions, dc, *batched = self._compiled_inputs(
            batch, center, generators, actions, None if tangents is None else (tangents[0],), action_dims=2,
            single=single, batched=batched)
        actions = actions.transpose(0, 1).clone(memory_format=torch.contiguous_format)  # [T, B, m] or [T, B, m (1 + k)]
        for dim in (0,) if single else (0, 1):
            torch._dynamo.mark_dynamic(actions, dim)
        with torch.no_grad():
            if tangents is not None:
                dc, k = dc[0], tangents[0].shape[-1]
                if k >= 2:  # a `finish` may specialise it (e.g. a program of as many variables)
                    torch._dynamo.maybe_mark_dynamic(dc, 2)
                    torch._dynamo.maybe_mark_dynamic(actions, 2)
            tail = tail or (None, None, None)
            finishing = {} if function is None else dict(finish=function, finish_inputs=(*batched, *args))
            out = loop(center, generators, actions, dc, *tail, **finishing)
        shapes = (((n, -1),) if tangents is not None and function is None else ()) + (
            ((-1,),) if tail[0] is not None else ())
        head, per_step = out[:len(out) - len(shapes)], out[len(out) - len(shapes):]  # per step: [T, B, ...]

        def batch_first(t: Tensor, shape: tuple) -> Tensor:
            return t[:, :count].transpose(0, 1).reshape(*batch, horizon, *shape)

        per_step = tuple(batch_first(t, shape) for t, shape in zip(per_step, shapes))
        if function is not None and len(batch) == 1 and center.shape[0] == count:  # no padding to undo
            return tuple(head) + per_step
        if function is not None:
            return tuple(t[:count].reshape(*batch, *t.shape[1:]) for t in head) + per_step
        with skip_value_checks():  # finite by construction
            sets = Zonotope(batch_first(head[0], (n,)), batch_first(head[1], (n, width)))
        return (sets, head[2][:count].reshape(batch)) + per_step

    def _loop(self, center: Tensor, generators: Tensor, actions: Tensor, tangent: Tensor | None = None,
              policy: Callable[[Tensor], Tensor] | None = None, plan_steps: Tensor | None = None,
              policy_tangent: Callable[[Tensor, Tensor], Tensor] | None = None,
              finish: Callable[..., tuple[Tensor, ...]] | None = None, finish_inputs: tuple = ()) -> tuple[Tensor, ...]:
        """:meth:`_step` over a plan as one ``while_loop``, traced as one graph when compiled: ``center [B, n]``,
        ``generators [B, n, max_generators]``, ``actions [T, B, m]`` to ``(centers [T, B, n], generators
        [T, B, n, max_generators], covered [B])``. With ``tangent`` ``[B, n, k]`` (the initial centre's
        directions), ``actions`` is ``[T, B, m (1 + k)]``, each action followed by its directions, and
        the centres' directions ``[T, B, n, k]`` follow. With ``policy``, the steps from ``plan_steps``
        (a 0-d tensor) on take ``policy(centre)`` instead of their row of ``actions`` (and with ``tangent``
        ``policy_tangent(centre, directions)`` instead of its directions), and the actions taken ``[T, B, m]``
        come last. With ``finish``, ``finish(centers [B, T, n], generators [B, T, n, max_generators], covered,
        *finish_inputs)``'s results replace the first three (:meth:`plan_sets`), and with ``tangent`` the directions
        too, which it takes as ``directions`` ``[B, T, n, k]``. The loop carries the current set only
        (its shapes fixed: the step reduces to ``max_generators`` columns) and writes every step's results into buffers
        allocated once (a ``while_loop`` may mutate captured tensors without gradients); carried, the buffers were
        copied whole at every step, and the Turtlebot's 16-step plans took 3-5 % longer."""
        horizon, m = actions.shape[0], self.widths[1]

        def more(i: Tensor, *_) -> Tensor:
            return i < horizon

        centers, sets = center.new_zeros(horizon, *center.shape), generators.new_zeros(horizon, *generators.shape)
        directions = None if tangent is None else tangent.new_zeros(horizon, *tangent.shape)
        taken = None if policy is None else center.new_zeros(horizon, center.shape[0], m)

        def step(i: Tensor, center: Tensor, generators: Tensor, covered: Tensor, *direction: Tensor):
            at = i.reshape(1)
            action = actions.index_select(0, at).squeeze(0)
            if tangent is not None:
                action = action.unflatten(-1, (m, -1))
                action, action_tangent = action[..., 0], action[..., 1:]
            if policy is not None:
                in_plan = i < plan_steps
                action = torch.where(in_plan, action, policy(center))
                taken.index_copy_(0, at, action.unsqueeze(0))
                if tangent is not None:
                    action_tangent = torch.where(in_plan, action_tangent, policy_tangent(center, direction[0]))
            if tangent is None:
                center, generators, inside = self._step(center, generators, action, None)
            else:
                center, generators, inside, moved = self._step(center, generators, action,
                                                               (direction[0], action_tangent))
                directions.index_copy_(0, at, moved.unsqueeze(0))
                direction = (moved,)
            centers.index_copy_(0, at, center.unsqueeze(0))
            sets.index_copy_(0, at, generators.unsqueeze(0))
            return (i + 1, center, generators, covered & inside, *direction)

        start = (torch.zeros((), dtype=torch.long, device=center.device), center, generators,
                 torch.ones(center.shape[0], dtype=torch.bool, device=center.device))
        if tangent is not None:
            start += (tangent,)
        covered = while_loop(more, step, start)[3]
        if finish is None:
            head = (centers, sets, covered, *((directions,) if tangent is not None else ()))
        else:
            along = {} if tangent is None else {"directions": directions.transpose(0, 1)}
            head = finish(centers.transpose(0, 1), sets.transpose(0, 1), covered, *finish_inputs, **along)
        return (*head, *((taken,) if policy is not None else ()))

    def _run_compiled(self, center: Tensor, generators: Tensor, action: Tensor,
                      tangents: tuple[Tensor, Tensor] | None) -> tuple[Tensor, ...]:
        """The compiled step on the inputs :meth:`_compiled_inputs` makes (one graph per use: inference,
        tangents, autograd)."""
        batch = center.shape[:-1]
        if generators.shape[:-2] != batch or action.shape[:-1] != batch:
            batch = torch.broadcast_shapes(batch, generators.shape[:-2], action.shape[:-1])
        count = batch.numel()
        n, width = self.state_dim, self.max_generators
        inputs = self._compiled_inputs(batch, center, generators, action, tangents)
        if tangents is not None and inputs[3][0].shape[-1] >= 2:  # one graph for every plan length
            for tangent in inputs[3]:
                torch._dynamo.mark_dynamic(tangent, tangent.ndim - 1)
        differentiable = torch.is_grad_enabled() and any(
            t.requires_grad for t in (*inputs[:3], *(inputs[3] or ())))
        with torch.set_grad_enabled(differentiable):  # one graph for inference, whatever the grad mode
            out = self._compiled[tangents is not None](*inputs)
        if count == len(out[0]) and len(batch) == 1:
            return out
        shapes = ((n,), (n, width), (), (n, out[-1].shape[-1]))
        return tuple(t[:count].reshape(*batch, *shape) for t, shape in zip(out, shapes))

    def _compiled_inputs(self, batch: torch.Size, center: Tensor, generators: Tensor, action: Tensor,
                         tangents: tuple[Tensor, Tensor] | None, action_dims: int = 1, single: bool = False,
                         batched: tuple[Tensor, ...] = ()) -> tuple:
        """Inputs on shapes that keep one compiled graph: a flat, contiguous batch of at least 2 (sizes 0 and
        1 are specialised by the compiler) marked dynamic, never a view (a view's guards read its base),
        and exactly ``max_generators`` columns (zero padding; a wider input is reduced first), so the
        reduction takes the same branch at every step. ``action`` has ``action_dims`` event dims. With
        ``single`` (a batch of one), a batch of exactly 1, for a graph of its own. ``batched`` (tensors with the
        batch dims first) follow, flattened alike."""
        count, width = batch.numel(), self.max_generators
        rows = 1 if single else max(count, 2)

        def flat(tensor: Tensor, event: int) -> Tensor:
            if tensor.ndim != event + 1 or tensor.shape[0] != rows or not tensor.is_contiguous():
                tensor = tensor.expand(*batch, *tensor.shape[tensor.ndim - event:]).reshape(-1, *tensor.shape[-event:])
                tensor = tensor.expand(rows, *tensor.shape[1:]).contiguous()
            tensor = plain_layout(tensor)  # one kind of input: no view, no odd strides on dims of size 1
            if not single:
                torch._dynamo.mark_dynamic(tensor, 0)
            return tensor

        if generators.shape[-1] < width:  # finite by construction: no value checks
            generators = torch.nn.functional.pad(generators, (0, width - generators.shape[-1]))
        elif generators.shape[-1] > width:
            generators = reduce_girard(generators, width)
        return (flat(center, 1), flat(generators, 2), flat(action, action_dims),
                None if tangents is None else tuple(flat(t, 2) for t in tangents),
                *(flat(t, t.ndim - len(batch)) for t in batched))

    def _step(self, center: Tensor, generators: Tensor, action: Tensor,
              tangents: tuple[Tensor, Tensor] | None, budget: dict | None = None) -> tuple[Tensor, ...]:
        """The step itself (:meth:`__call__`'s arguments and results), traced as one graph when compiled. ``budget``
        (eager): a dict that receives the parts of the step's error (:meth:`error_budget`)."""
        cells, n = self.cells, self.state_dim
        z_raw = torch.cat((center.index_select(-1, self.free), action), dim=-1)  # [..., d]
        g_free = generators.index_select(-2, self.free)  # [..., n_F, p] (actions are exact)
        # the exact interval radius per direction [..., F]
        ranges = small_matmul(self.projection_free, g_free).abs().sum(-1)
        phi_radius, hinge_radius, factor_radius = ranges.split(self.sizes, -1)
        phi = small_matmul(z_raw.unsqueeze(-2), self.projection).squeeze(-2) - self.knots
        phi, hinge_center, factor_center = phi.split(self.sizes, -1)
        slope, offset_h, feature_low, feature_high = relu_relaxation(hinge_center.unflatten(-1, (n, self.n_hinges)),
                                                                     hinge_radius.unflatten(-1, (n, self.n_hinges)))
        factors = (n, self.n_products, 2)
        factor_slope, constant, product_error, low, high = product_relaxation(factor_center.unflatten(-1, factors),
                                                                              factor_radius.unflatten(-1, factors))
        feature_low, feature_high = torch.cat((feature_low, low), -1), torch.cat((feature_high, high), -1)
        z_center = z_raw * self.inv_scale
        z_radius = torch.cat((g_free.abs().sum(-1) * self.inv_scale_free, torch.zeros_like(action)), dim=-1)
        gaps = leaf_gaps(*self.boxes, phi, phi_radius)
        near = self._near(gaps[0].detach()) if torch.compiler.is_compiling() else None
        distance = leaf_distance(cells, None, z_center.detach(), z_radius.detach(), layout=self.layout, near=near)
        index, errors, covered = leaf_bounds(cells, z_center, z_radius, phi_radius, feature_low, feature_high, distance,
                                             phi, gaps, self.slopes_by_input, terms=budget)
        A, B, offset, theta, theta_p = self.leaf_rows[index + self.row_offset].split(self.widths, dim=-1)
        # the relaxations relu(s) ∈ λ s + μ ± μ and s1 s2 ∈ λ1 s1 + λ2 s2 + κ ± ε fold into the leaf's
        # model
        along = (small_matmul((theta * slope).unsqueeze(-2), self.hinge_directions)
                 + small_matmul((theta_p.unsqueeze(-1) * factor_slope).flatten(-2).unsqueeze(-2),
                                self.product_rows)).squeeze(-2)
        shift = constant - (factor_slope * self.product_knots).sum(-1)
        offset = (offset.squeeze(-1) + (theta * (offset_h - slope * cells.hinge_knots)).sum(-1)
                  + (theta_p * shift).sum(-1))
        relaxation = (theta.abs() * offset_h).sum(-1) + (theta_p.abs() * product_error).sum(-1)
        errors = errors + relaxation
        A = A.index_add(-1, self.free, along[..., :len(self.inv_scale_free)])
        B = B + along[..., len(self.inv_scale_free):]
        new_center = small_matmul(A, center.unsqueeze(-1)) + small_matmul(B, action.unsqueeze(-1))
        new_center = new_center.squeeze(-1) + offset
        carried = small_matmul(A, generators)
        moved = None if tangents is None else self._tangents(center, new_center, A, B, *tangents)
        if self.body_frame is None:
            new = (torch.diag_embed(errors + self.noise_radius),)
        else:
            new_center, carried, new = self._rotate(center, generators, new_center, carried, errors)
        if self.noise_generators is not None:
            new = (*new, self.noise_generators.expand(*new_center.shape, -1))
        generators = torch.cat((carried, *new), dim=-1)
        if budget is not None:
            budget.update(relaxation=relaxation, carried=carried.abs().sum(-1),
                          added=generators[..., carried.shape[-1]:].abs().sum(-1))
        if self.max_generators is not None and generators.shape[-1] > self.max_generators:
            generators = girard_columns(generators, self.max_generators)  # finite by construction
        return (new_center, generators, covered) if tangents is None else (new_center, generators, covered, moved)

    def error_budget(self, center: Tensor, generators: Tensor, actions: Tensor) -> dict[str, Tensor]:
        """Where the sets of a plan get their width: the eager steps under ``actions`` ``[..., T, m]`` from
        ``Z(center [..., n], generators [..., n, p])``, each step's parts stacked ``[..., T, n]``
        (:meth:`DataDrivenReach.error_budget <torchrl_brsl.reach.DataDrivenReach.error_budget>`)."""
        steps, after = [], center.ndim - 1  # the plan's dim after the batch dims
        for action in actions.unbind(-2):
            budget = {}
            center, generators, covered = self._step(center, generators, action, None, budget)
            steps.append({**budget, "radius": generators.abs().sum(-1), "covered": covered})
        return {name: torch.stack([step[name] for step in steps], after) for name in steps[0]}

    def _near(self, gaps: Tensor) -> Tensor:
        """The leaves whose data a compiled step searches, ``[..., n, K]``, from the set's ``gaps`` to every leaf
        ``[..., n, M]``: the :data:`~torchrl_brsl.reach.cells.NEAR_LEAVES` it meets most deeply, or every leaf where
        there are no more (in their own order, without a ``topk``: a call out of the compiled kernels at every step)."""
        if self.near_leaves == gaps.shape[-1]:
            return torch.arange(gaps.shape[-1], device=gaps.device).expand(gaps.shape)
        return gaps.topk(self.near_leaves, largest=False).indices

    def _tangents(self, center: Tensor, body_center: Tensor, A: Tensor, B: Tensor, dc: Tensor, du: Tensor) -> Tensor:
        """``d new centre = J_c dc + J_u du`` ``[..., n, k]``: the affine part of the step (``A``, ``B`` with the
        relaxations folded in) and, with a body frame, the first-order terms of the rotation ``M(q) h``
        (``body_center`` the step's centre before it)."""
        moved = A @ dc + B @ du
        if self.body_frame is None:
            return moved
        frame, index, pairs = self.body_frame, self.rotated, (-1, 2)
        q0, q_tangents, _ = frame.heading_form(center, dc)
        zeros = q0.new_zeros(*q0.shape[:-1], 1, 2)
        h0 = (body_center.index_select(-1, index) - self.noise_center[self.rotated]).unflatten(-1, pairs)
        _, rotated, _, _ = frame.rotate((q0.unsqueeze(-2), q_tangents.unsqueeze(-3), zeros), h0,
                                        moved.index_select(-2, index).unflatten(-2, pairs), torch.zeros_like(h0))
        rotated = rotated.flatten(-3, -2) + self.moves.unsqueeze(-1) * dc.index_select(-2, index)
        return moved.index_copy(-2, index, rotated)

    def _rotate(self, center: Tensor, generators: Tensor, new_center: Tensor, carried: Tensor,
                errors: Tensor) -> tuple[Tensor, Tensor, tuple[Tensor, Tensor]]:
        """Turn the body-frame outputs of a step into world-frame ones.

        ``new_center`` ``[..., n]``, ``carried`` ``[..., n, p]`` (the old generators mapped) and
        ``errors`` ``[..., n]`` (the leaves' interval radii) hold the body-frame model on the
        ``P`` rotated pairs. Returns the world-frame centre and carried generators (a position
        adds its old value) and the new columns: the error ``[..., n, n]`` (diagonal but for the
        rotated pairs' 2 x 2 blocks) and the enclosure's remainder on the rotated dims,
        ``[..., n, 2P]``, each with the noise's radii added (the rotated dims' to the box).
        """
        frame, w_c, index = self.body_frame, self.noise_center[self.rotated], self.rotated
        q0, q_gens, q_error = frame.heading_form(center, generators)
        heading = (q0.unsqueeze(-2), q_gens.unsqueeze(-3), q_error.unsqueeze(-2))  # one heading for every pair
        pairs = (-1, 2)
        rotated, gens, blocks, box = frame.rotate(
            heading, (new_center.index_select(-1, index) - w_c).unflatten(-1, pairs),
            carried.index_select(-2, index).unflatten(-2, pairs), errors.index_select(-1, index).unflatten(-1, pairs))
        moves = self.moves * center.index_select(-1, index)
        new_center = new_center.index_copy(-1, index, rotated.flatten(-2) + w_c + moves)
        moved = gens.flatten(-3, -2) + self.moves.unsqueeze(-1) * generators.index_select(-2, index)
        carried = carried.index_copy(-2, index, moved)
        place = self.place_pairs  # each block placed, as sums that fuse when compiled (einsum: a BLAS call per step)
        blocks = small_matmul(small_matmul(place, blocks), place, transpose_b=True).sum(-3)
        error = torch.diag_embed(errors * self.unrotated + self.noise_radius) + blocks
        box_columns = (box.flatten(-2) + self.box_noise).unsqueeze(-2) * self.place
        return new_center, carried, (error, box_columns)


def stack_steps(centers: Sequence[Tensor], generators: Sequence[Tensor]) -> Zonotope:
    """The sets of successive steps, ``[..., n]`` centres and ``[..., n, p_j]`` generators each,
    as one :class:`Zonotope` of batch ``[..., H]`` (generators zero-padded to the widest)."""
    width = max(g.shape[-1] for g in generators)
    with skip_value_checks():  # built from the validated model
        return Zonotope(torch.stack(list(centers), -2), torch.stack([pad_generators(g, width) for g in generators], -3))
