"""Reproducible triangle-pair generators shared by the tests and the benchmark scripts."""

from __future__ import annotations

import math

import torch

__all__ = ["random_rotations", "random_separated_pairs"]


def random_rotations(k: int, generator: torch.Generator, dtype=torch.float64) -> torch.Tensor:
    """(k, 3, 3) uniformly random rotation matrices (QR of Gaussian matrices with sign fix)."""
    q, r = torch.linalg.qr(torch.randn(k, 3, 3, generator=generator, dtype=dtype))
    q = q * torch.sign(torch.diagonal(r, dim1=-2, dim2=-1))[:, None, :]
    det = torch.linalg.det(q)
    q[:, :, 0] *= det[:, None]
    return q


def random_separated_pairs(
    k: int,
    *,
    gap: tuple[float, float] = (2e-3, 1.0),
    size: float = 1.0,
    seed: int = 0,
    dtype: torch.dtype = torch.float64,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Random triangle pairs separated by a slab of log-uniform width along a random direction.

    Each triangle has three Gaussian vertices (scale ``size``) in a random orientation; triangle b is pushed along a
    random unit direction u until min_b(u.x) - max_a(u.x) equals the slab width, so the true distance is at least
    the slab width (equal for vertex-face contacts along u).

    Returns:
        tri_a (k, 3, 3), tri_b (k, 3, 3), slab widths (k,).
    """
    g = torch.Generator().manual_seed(seed)
    a = size * torch.randn(k, 3, 3, generator=g, dtype=torch.float64)
    b = size * torch.randn(k, 3, 3, generator=g, dtype=torch.float64)
    u = torch.randn(k, 3, generator=g, dtype=torch.float64)
    u = u / u.norm(dim=-1, keepdim=True)
    lo, hi = math.log(gap[0]), math.log(gap[1])
    w = torch.exp(lo + (hi - lo) * torch.rand(k, generator=g, dtype=torch.float64))
    shift = (a @ u[:, :, None]).amax((1, 2)) - (b @ u[:, :, None]).amin((1, 2)) + w
    b = b + shift[:, None, None] * u[:, None, :]
    return a.to(dtype), b.to(dtype), w.to(dtype)
