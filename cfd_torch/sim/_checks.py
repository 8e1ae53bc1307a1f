"""Input checks of the simulator's public functions: ValueErrors naming the argument."""

from __future__ import annotations

import torch

from .types import Params

__all__ = ["check_state_tensor", "check_params"]


def check_state_tensor(x: object, name: str, n: int, cols: int = 6, batch: int | None = None) -> None:
    """x must be a finite float tensor of shape (n, cols) or (B, n, cols) (B = ``batch`` when given)."""
    if not isinstance(x, torch.Tensor):
        raise TypeError(f"{name} must be a torch.Tensor, got {type(x).__name__}")
    ok = (
        x.shape[-2:] == (n, cols)
        and x.dim() in (2, 3)
        and (batch is None or x.dim() == 2 or x.shape[0] == batch)
    )
    if not ok:
        want = f"({n}, {cols})" + (f" or ({batch}, {n}, {cols})" if batch else f" or (B, {n}, {cols})")
        raise ValueError(f"{name} must have shape {want}, got {tuple(x.shape)}")
    if x.dtype not in (torch.float32, torch.float64):
        raise ValueError(f"{name} must be float32 or float64, got {x.dtype}")
    bad = ~torch.isfinite(x).all(-1)
    if bool(bad.any()):
        at = tuple(int(i) for i in torch.nonzero(bad)[0])
        raise ValueError(
            f"{name} contains NaN or inf (first at {'scene, body' if x.dim() == 3 else 'body'} {at})"
        )


def check_params(params: Params, B: int, Nd: int, device: torch.device, batched: bool) -> Params:
    """Finite, physical, on the state's device, each field shared or per scene; returned with a batch dimension B:
    mass > 0, friction >= 0, the symmetric part of S positive semi-definite with a positive definite inertia
    tr(S) I - S."""
    for name, x in (
        ("mass", params.mass),
        ("second_moment", params.second_moment),
        ("friction", params.friction),
    ):
        if not isinstance(x, torch.Tensor) or not x.is_floating_point():
            raise ValueError(f"params.{name} must be a floating-point tensor")
        if x.device != device:
            raise ValueError(f"params.{name} is on {x.device}, the state on {device}")
        if not bool(torch.isfinite(x).all()):
            raise ValueError(f"params.{name} contains NaN or inf")
    fields = []
    for name, x, shape in (("mass", params.mass, (Nd,)), ("second_moment", params.second_moment, (Nd, 3, 3)),
                           ("friction", params.friction, ())):  # fmt: skip
        if x.shape == shape:
            x = x.expand(B, *shape)  # shared by the batch
        elif x.shape != (B, *shape) or not batched:
            want = f"{shape} or {(B, *shape)}" if batched else f"{shape}"
            raise ValueError(f"params.{name} must have shape {want}, got {tuple(x.shape)}")
        fields.append(x)
    params = Params(*fields)
    if not bool((params.mass > 0).all()):
        raise ValueError("params.mass must be positive")
    if bool((params.friction.detach() < 0).any()):
        raise ValueError("params.friction must be >= 0")
    S = params.second_moment.detach().to(torch.float64).reshape(-1, 3, 3)
    S = 0.5 * (S + S.transpose(1, 2))  # the step uses the symmetric part
    eye = torch.eye(3, dtype=S.dtype, device=S.device)
    inertia = torch.diagonal(S, dim1=1, dim2=2).sum(-1)[:, None, None] * eye - S
    if bool((torch.linalg.eigvalsh(S) < -1e-12 * S.abs().amax((1, 2))[:, None]).any()) or not bool(
        (torch.linalg.eigvalsh(inertia) > 0).all()
    ):
        raise ValueError(
            "params.second_moment must be positive semi-definite with a positive definite inertia"
        )
    return params
