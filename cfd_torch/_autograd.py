"""Autograd Functions shared by the contact potentials whose derivatives are known in closed form, and the
potentials' contract with torch.func.

A potential ``value(q)`` with a closed-form gradient and Hessian is attached to autograd by
:class:`ClosedFormPotential`; its backward is :class:`ClosedFormGrad`, whose backward is the closed-form
Hessian-vector product, differentiable in its vector (so ``torch.autograd.functional.hvp``'s double-backward works);
a third derivative raises through :func:`refuse_third_order` (also used by ``pair_potential``, whose Hessian is
implicit).

torch.func: the Functions are in the new style (``forward`` without ctx, ``setup_context``), so ``torch.func.grad``
and ``torch.func.jacrev`` work, nested to second order (grad of grad, jacrev of jacrev) like ``torch.autograd``, and
a third level raises as there. Inside ``forward`` the inputs are plain tensors with no transform active, which the
numba kernels need; code outside the Functions that needs plain tensors (validation, precomputation, caches) runs in
:func:`outside_transforms` on :func:`plain` values. ``torch.func.vmap`` and forward mode (``jvp``, ``jacfwd``,
``hessian``) raise ``NotImplementedError`` saying so. The functorch hooks used here are private torch APIs
(``torch._C._functorch``, ``torch._functorch.pyfunctorch``).
"""

from __future__ import annotations

import contextlib
from collections.abc import Callable

import torch
from torch._functorch.pyfunctorch import temporarily_clear_interpreter_stack

_functorch = torch._C._functorch


def plain(x: torch.Tensor) -> torch.Tensor:
    """The plain tensor under torch.func wrappers, to read values from (validation; kernels that need storage).

    Use it inside :func:`outside_transforms` (otherwise every op on it is wrapped again). Not connected to any
    transform: the values only. Under ``grad``/``jacrev`` levels it has the input's shape; each ``vmap`` level adds
    its batch dimension in front (outermost vmap first), so it holds all the vmapped instances' values.
    """
    bdims = []
    while _functorch.is_functorch_wrapped_tensor(x):
        if _functorch.is_batchedtensor(x):
            bdims.append(_functorch.maybe_get_bdim(x))
        x = _functorch.get_unwrapped(x)
    if not bdims:
        return x
    # the innermost level's batch dimension indexes the physical tensor; each outer level's indexes what is left
    axes = list(range(x.dim()))
    front = [axes.pop(b) for b in reversed(bdims)]
    return x.permute(*front, *axes)


def legacy_batched(x: torch.Tensor) -> bool:
    """Whether ``x`` is one of autograd's own batched tensors (``jacobian(..., vectorize=True)``,
    ``is_grads_batched=True``), whose values cannot be read."""
    return _functorch.is_legacy_batchedtensor(x)


def outside_transforms() -> contextlib.AbstractContextManager:
    """Context in which code runs on plain tensors with torch.func's transforms set aside (the interpreter stack is
    emptied and restored on exit): inside, ops do not wrap their results, so tensors keep their storage (numpy
    views, numba kernels) and may be cached, and custom Functions run as under plain autograd. Read inputs through
    :func:`plain`; do not operate on the transforms' wrapped tensors inside. A no-op when no transform is active
    (the common case costs well under a microsecond)."""
    if _functorch.peek_interpreter_stack() is None:
        return contextlib.nullcontext()
    return temporarily_clear_interpreter_stack()


def tracked(x: torch.Tensor) -> bool:
    """Whether a result computed from ``x`` must be attached to a differentiable Function: ``x`` requires grad
    with autograd on, carries a torch.func transform (grad, jacrev, jvp), or has a forward-mode tangent."""
    if _functorch.is_functorch_wrapped_tensor(x):
        return True
    if x.requires_grad and torch.is_grad_enabled():
        return True
    return has_tangent(x)


def has_tangent(x: torch.Tensor) -> bool:
    """Whether ``x`` carries a forward-mode tangent (``torch.autograd.forward_ad``, or a ``torch.func.jvp`` /
    ``jacfwd`` level); forward mode runs under ``torch.no_grad`` too."""
    return torch.autograd.forward_ad.unpack_dual(x).tangent is not None


def vmap_error(name: str) -> NotImplementedError:
    return NotImplementedError(
        f"{name} does not support torch.func.vmap (its solvers need plain tensors); pass the batch as leading "
        "dimensions of the inputs, or loop"
    )


def forward_mode_error(name: str, order: str = "to second order") -> NotImplementedError:
    return NotImplementedError(
        f"{name} does not support forward-mode AD (torch.func.jvp, jacfwd, hessian); use reverse mode "
        f"(torch.autograd, torch.func.grad or jacrev, {order})"
    )


def _vmapped(x: object) -> bool:
    """Whether ``x`` is a tensor batched by torch.func.vmap at some level."""
    while isinstance(x, torch.Tensor) and _functorch.is_functorch_wrapped_tensor(x):
        if _functorch.is_batchedtensor(x):
            return True
        x = _functorch.get_unwrapped(x)
    return False


def refuse_vmap(name: str, *tensors: torch.Tensor) -> None:
    """Raise :func:`vmap_error` if one of ``tensors`` is batched by torch.func.vmap (at any level)."""
    if any(_vmapped(x) for x in tensors):
        raise vmap_error(name)


def refuse_transforms(message: str, *tensors: object) -> None:
    """Raise NotImplementedError(``message``) if one of ``tensors`` (non-tensors are skipped) is under any
    torch.func transform or carries a forward-mode tangent (``torch.autograd.forward_ad``): for code whose autograd
    Function is not in the new style and has no jvp."""
    for x in tensors:
        if isinstance(x, torch.Tensor) and (_functorch.is_functorch_wrapped_tensor(x) or has_tangent(x)):
            raise NotImplementedError(message)


def refuse_batched(message: str, *tensors: object) -> None:
    """Raise NotImplementedError(``message``) if one of ``tensors`` is batched by vmap: in a backward, the grad
    outputs of ``autograd.grad(..., is_grads_batched=True)`` and ``autograd.functional.jacobian(vectorize=True)``."""
    for x in tensors:
        # autograd's own batching (legacy batched tensors), or torch.func's
        if (isinstance(x, torch.Tensor) and legacy_batched(x)) or _vmapped(x):
            raise NotImplementedError(message)


# the message of values_only for a closed-form derivatives function ``name`` whose differentiable twin is ``diff``
VALUES_ONLY = (
    "{name}(...).{{field}} carries no gradient (closed-form derivatives are values, not connected to autograd or "
    "torch.func); differentiate {diff} instead, or .detach() the inputs"
)


def values_only(result: tuple, fields: tuple[str, ...], inputs: tuple, message: str) -> tuple:
    """``result`` (a NamedTuple) with its tensor ``fields`` made to refuse differentiation: where one of ``inputs``
    is tracked (see :func:`tracked`), a backward (or torch.func.grad) through such a field toward that input raises
    ``RuntimeError(message.format(field=...))`` instead of silently treating the field as a constant; an input with
    a forward-mode tangent raises ``NotImplementedError`` at the call. The fields then require grad (``.detach()``
    them for ``.numpy()``)."""
    live = [x for x in inputs if isinstance(x, torch.Tensor) and tracked(x)]
    if not live:
        return result
    changes = {}
    for f in fields:
        y = getattr(result, f)
        if isinstance(y, torch.Tensor):
            for x in live:
                y = refuse_derivative(y, x, message.format(field=f))
            changes[f] = y
    return result._replace(**changes)


Evaluate = Callable[[torch.Tensor, int], tuple]


class ClosedFormPotential(torch.autograd.Function):
    """value(q) for q (B, n) whose derivatives come from ``evaluate(q, order) -> (value (B,), grad (B, n),
    hess (B, n, n))`` in closed form; ``name`` (the public function) appears in the error messages.
    Backward: the closed-form gradient; under create_graph it comes from ClosedFormGrad, whose backward is the
    closed-form Hessian-vector product; a third derivative raises."""

    @staticmethod
    def forward(q: torch.Tensor, evaluate: Evaluate, name: str) -> torch.Tensor:
        v, _, _ = evaluate(q, 0)
        return v

    @staticmethod
    def setup_context(ctx, inputs, output):
        q, ctx.evaluate, ctx.name = inputs
        ctx.save_for_backward(q)

    @staticmethod
    def backward(ctx, gout):
        # d (gout . value) / dq = gout g(q), g from evaluate in closed form
        (q,) = ctx.saved_tensors
        if torch.is_grad_enabled():
            g, _ = ClosedFormGrad.apply(q, ctx.evaluate, ctx.name)
        else:
            _, g, _ = ctx.evaluate(q, 1)
        return gout[:, None] * g, None, None

    @staticmethod
    def vmap(info, in_dims, q, evaluate, name):
        raise vmap_error(name)

    @staticmethod
    def jvp(ctx, *tangents):
        raise forward_mode_error(ctx.name)


class ClosedFormGrad(torch.autograd.Function):
    """(grad (B, n), hess (B, n, n)) of a closed-form potential (see ClosedFormPotential); the Hessian output is not
    differentiable (it is what backward uses); backward: the Hessian-vector product."""

    @staticmethod
    def forward(q: torch.Tensor, evaluate: Evaluate, name: str) -> tuple[torch.Tensor, torch.Tensor]:
        _, g, h = evaluate(q, 2)
        return g, h

    @staticmethod
    def setup_context(ctx, inputs, output):
        q, _, ctx.name = inputs
        _, h = output
        ctx.mark_non_differentiable(h)
        ctx.save_for_backward(q, h)

    @staticmethod
    def backward(ctx, v, _):
        # d (v . g(q)) / dq = v^T H(q), H symmetric
        q, h = ctx.saved_tensors
        # (a matmul, not einsum: autograd.functional's vectorize=True has no batching rule for einsum)
        hv = (v[:, None, :] @ h)[:, 0]
        # under create_graph: differentiable in v (the product is linear in it), while H(q)'s own derivative in q
        # is not available: refused
        if torch.is_grad_enabled():
            hv = refuse_third_order(hv, q, ctx.name)
        return hv, None, None

    @staticmethod
    def vmap(info, in_dims, q, evaluate, name):
        raise vmap_error(name)

    @staticmethod
    def jvp(ctx, *tangents):
        raise forward_mode_error(ctx.name)


def refuse_third_order(hv: torch.Tensor, x: torch.Tensor, name: str) -> torch.Tensor:
    """A Hessian-vector product ``hv`` computed from the point ``x``, with its derivative in ``x`` (a third
    derivative) refused: any backward that reaches ``x`` through it raises a RuntimeError naming ``name``. Its
    derivative in the vector is ``hv``'s own (a Hessian-vector product is linear in the vector: keep ``hv``
    differentiable in it, and ``torch.autograd.functional.hvp`` works).

    ``x`` must be the differentiable point itself (a tensor that requires grad when the Hessian's own derivative
    would be needed): an input that does not require grad leaves the refusal out of the graph, and the third
    derivative would silently be dropped. Under vmap (e.g. ``jacrev`` of ``jacrev``) the added term stays zero.
    """
    message = (
        f"{name}: third derivatives are not implemented; the second derivative is exact but cannot be "
        "differentiated again"
    )
    return refuse_derivative(hv, x, message)


def refuse_derivative(y: torch.Tensor, x: torch.Tensor, message: str) -> torch.Tensor:
    """``y`` unchanged, with a zero term added whose derivative in ``x`` raises ``RuntimeError(message)``: a
    backward that reaches ``x`` through the result raises, one that reaches only ``y``'s other inputs does not."""
    return y + _Refusal.apply(x, message)


class _Refusal(torch.autograd.Function):
    """A 0-d zero that depends on ``x``, whose backward raises (see :func:`refuse_derivative`)."""

    generate_vmap_rule = True

    @staticmethod
    def forward(x: torch.Tensor, message: str) -> torch.Tensor:
        return x.new_zeros(())

    @staticmethod
    def setup_context(ctx, inputs, output):
        ctx.message = inputs[1]

    @staticmethod
    def backward(ctx, grad):
        raise RuntimeError(ctx.message)

    @staticmethod
    def jvp(ctx, *tangents):
        raise NotImplementedError(f"forward-mode AD: {ctx.message}")
