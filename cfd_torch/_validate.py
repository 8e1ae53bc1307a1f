"""Input checks shared by the public functions: each raises a ``ValueError`` naming the argument and the first
offending batch index. Values are read from the plain tensor under torch.func wrappers (see ``_autograd.plain``), so
the checks run unchanged under ``torch.func.grad``."""

from __future__ import annotations

import math

import numba
import torch

from ._autograd import outside_transforms, plain

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
    with outside_transforms():
        x = plain(x)
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
    tol = _DEGENERACY_EPS_MULTIPLE * torch.finfo(tri.dtype).eps
    with outside_transforms():
        _check_triangle_values(plain(tri), name, tol)


def _check_triangle_values(tri: torch.Tensor, name: str, tol: float) -> None:
    if tri.device.type == "cpu":  # one fused pass (the tensor form below makes ~20 passes over the data)
        flat = tri.detach().reshape(-1, 3, 3).contiguous()
        code = torch.empty(flat.shape[0], dtype=torch.uint8)
        kernel = _triangle_codes_nb if flat.shape[0] >= 100_000 else _triangle_codes_serial
        kernel(flat.numpy(), float(tol), code.numpy())
        code = code.reshape(tri.shape[:-2])
        nonfinite, degenerate = code == 1, code == 2
    else:
        e1 = tri[..., 1, :] - tri[..., 0, :]
        e2 = tri[..., 2, :] - tri[..., 0, :]
        e3 = tri[..., 2, :] - tri[..., 1, :]
        area2_sq = (torch.linalg.cross(e1, e2) ** 2).sum(-1)  # (2 area)^2
        longest_sq = torch.maximum(torch.maximum((e1 * e1).sum(-1), (e2 * e2).sum(-1)), (e3 * e3).sum(-1))
        degenerate = ~(area2_sq > (tol * longest_sq) ** 2)  # also True for coincident vertices and for NaN
        if not bool(degenerate.any()):
            return
        nonfinite = ~torch.isfinite(tri).flatten(-2).all(-1)
    if bool(nonfinite.any()):
        raise ValueError(
            f"{name} contains NaN or inf coordinates (triangle at batch index {_index_str(nonfinite)}, "
            f"{int(nonfinite.sum())} triangles)"
        )
    if bool(degenerate.any()):
        raise ValueError(
            f"{name} has degenerate triangles (collinear or coincident vertices relative to the triangle's size), "
            f"first at batch index {_index_str(degenerate)}, {int(degenerate.sum())} in all"
        )


@numba.njit(parallel=True, cache=True, error_model="numpy")
def _triangle_codes_nb(tri, tol, code):
    """code[k] = 1 if triangle k has a NaN/inf coordinate, 2 if 2 area <= tol * longest edge^2, else 0."""
    for k in numba.prange(tri.shape[0]):
        t = tri[k]
        finite = True
        for i in range(3):
            for j in range(3):
                if not math.isfinite(t[i, j]):
                    finite = False
        if not finite:
            code[k] = 1
            continue
        ax, ay, az = t[1, 0] - t[0, 0], t[1, 1] - t[0, 1], t[1, 2] - t[0, 2]
        bx, by, bz = t[2, 0] - t[0, 0], t[2, 1] - t[0, 1], t[2, 2] - t[0, 2]
        cx, cy, cz = t[2, 0] - t[1, 0], t[2, 1] - t[1, 1], t[2, 2] - t[1, 2]
        nx, ny, nz = ay * bz - az * by, az * bx - ax * bz, ax * by - ay * bx
        area2_sq = nx * nx + ny * ny + nz * nz
        longest_sq = max(
            ax * ax + ay * ay + az * az, bx * bx + by * by + bz * bz, cx * cx + cy * cy + cz * cz
        )
        code[k] = 0 if area2_sq > (tol * longest_sq) ** 2 else 2


def check_positive(value: float, name: str) -> None:
    if not (isinstance(value, (int, float)) and value > 0 and value < float("inf")):
        raise ValueError(f"{name} must be a finite positive number, got {value!r}")


_triangle_codes_serial = numba.njit(cache=True, error_model="numpy")(_triangle_codes_nb.py_func)
