"""Input checks shared by the public functions: each raises a ``ValueError`` naming the argument and the first
offending batch index."""

from __future__ import annotations

import torch

# A triangle is degenerate when twice its area is below this many machine epsilons of its longest edge squared
# (scale-free: a tiny well-shaped triangle is valid, a needle or a collinear triple is not).
_DEGENERACY_EPS_MULTIPLE = 100.0


def _index_str(mask: torch.Tensor) -> str:
    idx = torch.nonzero(mask)[0]
    return "(" + ", ".join(str(int(i)) for i in idx) + ")"


def check_finite_tensor(x: object, name: str, *, allow_inf: bool = False) -> None:
    """Require a floating-point tensor without NaN (and without inf unless ``allow_inf``)."""
    if not isinstance(x, torch.Tensor):
        raise TypeError(f"{name} must be a torch.Tensor, got {type(x).__name__}")
    if not x.is_floating_point():
        raise ValueError(f"{name} must have a floating dtype (float32 or float64), got {x.dtype}")
    bad = torch.isnan(x) if allow_inf else ~torch.isfinite(x)
    if bool(bad.any()):
        what = "NaN" if allow_inf else "NaN or inf"
        raise ValueError(
            f"{name} contains {what} (first at index {_index_str(bad)}, {int(bad.sum())} entries)"
        )


def check_triangles(tri: object, name: str) -> None:
    """Validate a ``(..., 3, 3)`` batch of triangles: dtype, shape, finiteness and non-degeneracy.

    Args:
        tri: (..., 3, 3) vertices (vertex index, then xyz).
        name: argument name used in error messages.
    """
    if not isinstance(tri, torch.Tensor):
        raise TypeError(f"{name} must be a torch.Tensor, got {type(tri).__name__}")
    if tri.dim() < 2 or tri.shape[-2:] != (3, 3):
        raise ValueError(f"{name} must have shape (..., 3, 3) (three vertices, xyz), got {tuple(tri.shape)}")
    if tri.dtype not in (torch.float32, torch.float64):
        raise ValueError(f"{name} must be float32 or float64, got {tri.dtype}")
    # One pass: the shape test below is False for NaN/inf coordinates as well, so finiteness is only diagnosed
    # (an extra pass) when something failed.
    e1 = tri[..., 1, :] - tri[..., 0, :]
    e2 = tri[..., 2, :] - tri[..., 0, :]
    e3 = tri[..., 2, :] - tri[..., 1, :]
    area2_sq = (torch.linalg.cross(e1, e2) ** 2).sum(-1)  # (2 area)^2
    longest_sq = torch.maximum(torch.maximum((e1 * e1).sum(-1), (e2 * e2).sum(-1)), (e3 * e3).sum(-1))
    tol = _DEGENERACY_EPS_MULTIPLE * torch.finfo(tri.dtype).eps
    bad = ~(area2_sq > (tol * longest_sq) ** 2)  # also True for coincident vertices (0 > 0) and for NaN
    if not bool(bad.any()):
        return
    nonfinite = ~torch.isfinite(tri).flatten(-2).all(-1)
    if bool(nonfinite.any()):
        raise ValueError(
            f"{name} contains NaN or inf coordinates (triangle at batch index {_index_str(nonfinite)}, "
            f"{int(nonfinite.sum())} triangles)"
        )
    raise ValueError(
        f"{name} has degenerate triangles (collinear or coincident vertices relative to the triangle's size), "
        f"first at batch index {_index_str(bad)}, {int(bad.sum())} in all"
    )


def check_positive(value: float, name: str) -> None:
    if not (isinstance(value, (int, float)) and value > 0 and value < float("inf")):
        raise ValueError(f"{name} must be a finite positive number, got {value!r}")
