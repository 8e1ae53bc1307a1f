"""Autograd Functions shared by the contact potentials whose derivatives are known in closed form.

A potential ``value(q)`` with a closed-form gradient and Hessian is attached to autograd by
:class:`ClosedFormPotential`; its backward is :class:`ClosedFormGrad`, whose backward is the closed-form
Hessian-vector product; a third derivative raises through :class:`RefuseThirdOrder` (also used by
``pair_potential``, whose Hessian is implicit).
"""

from __future__ import annotations

import torch


class ClosedFormPotential(torch.autograd.Function):
    """value(q) for q (B, n) whose derivatives come from ``evaluate(q, order) -> (value (B,), grad (B, n),
    hess (B, n, n))`` in closed form; ``name`` (the public function) appears in the third-derivative error.
    Backward: the closed-form gradient; under create_graph it comes from ClosedFormGrad, whose backward is the
    closed-form Hessian-vector product; a third derivative raises."""

    @staticmethod
    def forward(ctx, q, evaluate, name):
        v, _, _ = evaluate(q, 0)
        ctx.save_for_backward(q)
        ctx.evaluate = evaluate
        ctx.name = name
        return v

    @staticmethod
    def backward(ctx, gout):
        # d (gout . value) / dq = gout g(q), g from evaluate in closed form
        (q,) = ctx.saved_tensors
        if torch.is_grad_enabled():
            g = ClosedFormGrad.apply(q, ctx.evaluate, ctx.name)
        else:
            _, g, _ = ctx.evaluate(q, 1)
        return gout[:, None] * g, None, None


class ClosedFormGrad(torch.autograd.Function):
    """grad(q) (B, n) of a closed-form potential (see ClosedFormPotential); backward: the Hessian-vector product."""

    @staticmethod
    def forward(ctx, q, evaluate, name):
        _, g, h = evaluate(q, 2)
        ctx.save_for_backward(q, h)
        ctx.name = name
        return g

    @staticmethod
    def backward(ctx, v):
        # d (v . g(q)) / dq = v^T H(q), H symmetric
        q, h = ctx.saved_tensors
        hv = torch.einsum("bi,bij->bj", v, h)
        # under create_graph H(q) would need its own derivative in q, which is not available: refuse it
        if torch.is_grad_enabled():
            hv = RefuseThirdOrder.apply(hv, q, v, ctx.name)
        return hv, None, None


class RefuseThirdOrder(torch.autograd.Function):
    """Identity on a Hessian-vector product ``hv`` computed from the point ``x`` and the vector ``v``; its backward
    (a third derivative, or the derivative of the product in ``v``) raises a RuntimeError naming ``name``.

    ``x`` must be the differentiable point itself (a tensor that requires grad when the Hessian's own derivative
    would be needed): an input that does not require grad leaves the refusal out of the graph, and the third
    derivative would silently be dropped.
    """

    @staticmethod
    def forward(ctx, hv, x, v, name):
        ctx.name = name
        return hv.clone()

    @staticmethod
    def backward(ctx, grad):
        raise RuntimeError(
            f"{ctx.name}: third derivatives are not implemented; the second derivative is exact but cannot be "
            "differentiated again"
        )
