"""Autograd Functions shared by the contact potentials whose derivatives are known in closed form.

A potential ``value(q)`` with a closed-form gradient and Hessian is attached to autograd by
:class:`ClosedFormPotential`; its backward is :class:`ClosedFormGrad`, whose backward is the closed-form
Hessian-vector product; a third derivative raises through :class:`RefuseThirdOrder`.
"""

from __future__ import annotations

import torch


class ClosedFormPotential(torch.autograd.Function):
    """value(q) for q (B, n) whose derivatives come from ``evaluate(q, order) -> (value (B,), grad (B, n),
    hess (B, n, n))`` in closed form. Backward: the closed-form gradient; under create_graph it comes from
    ClosedFormGrad, whose backward is the closed-form Hessian-vector product; a third derivative raises."""

    @staticmethod
    def forward(ctx, q, evaluate):
        v, _, _ = evaluate(q, 0)
        ctx.save_for_backward(q)
        ctx.evaluate = evaluate
        return v

    @staticmethod
    def backward(ctx, gout):
        (q,) = ctx.saved_tensors
        if torch.is_grad_enabled():
            g = ClosedFormGrad.apply(q, ctx.evaluate)
        else:
            _, g, _ = ctx.evaluate(q, 1)
        return gout[:, None] * g, None


class ClosedFormGrad(torch.autograd.Function):
    @staticmethod
    def forward(ctx, q, evaluate):
        _, g, h = evaluate(q, 2)
        ctx.save_for_backward(h)
        return g

    @staticmethod
    def backward(ctx, v):
        (h,) = ctx.saved_tensors
        hv = torch.einsum("bi,bij->bj", v, h)  # symmetric Hessian: v^T H
        if torch.is_grad_enabled():
            hv = RefuseThirdOrder.apply(hv, v)
        return hv, None


class RefuseThirdOrder(torch.autograd.Function):
    @staticmethod
    def forward(ctx, hv, v):
        return hv.clone()

    @staticmethod
    def backward(ctx, grad):
        raise RuntimeError(
            "contact potential: third derivatives are not implemented; the Hessian is exact but cannot be "
            "differentiated again"
        )
