"""Central (contracted-cluster) potential and the quintic blend between it and the fine potential.

Contracting every vertex of a cluster onto its centre turns the exact pair potential into a closed form of the
centre distance ``r`` alone, the same for a triangle pair and for any pair of clusters (SPEC section 3)::

    P_c(r)     = 12 mu (1 + r^-1/2)^2
    P_c'(r)    = -12 mu (r^-3/2 + r^-2)                 < 0   (always repulsive)
    P_c''(r)   = 12 mu (3/2 r^-5/2 + 2 r^-3)           > 0

The quintic smoothstep ``Phi(s) = clip(6 s^5 - 15 s^4 + 10 s^3, 0, 1)`` has ``Phi'`` and ``Phi''`` zero at s = 0 and
s = 1, so a blend ``phi P_c + (1 - phi) P_fine`` with ``phi = Phi((r - d1) / (d2 - d1))`` is C2.

The band's width ``d2 - d1`` is ``max(eps d1, 2 delta)`` (:func:`band_width`): SPEC's ``eps d1``, but never less than
twice the margin delta. A far pair (r >= d2) gets the central term alone, finite, so its spheres must be farther
apart than delta, or the meshes below could be within the margin (where the potential is +inf) while the
potential stays finite and flat: two 80-face balls (d1 = 0.057 m, eps d1 = 0.57 mm < delta = 1 mm) meeting vertex
to vertex had P = P_c up to a gap of 0.57 mm and +inf just below, a wall with no barrier in front of it, against
which a Newton solve stalls. With a band of 2 delta, every triangle pair below a pair in the band's upper half is
more than delta apart, and the fine potential's barrier grows within the band.
"""

from __future__ import annotations

import torch

from .._autograd import outside_transforms, plain
from .._validate import check_finite_tensor, check_positive, check_stiffness, is_real
from ..config import DEFAULT_CONTACT

__all__ = ["central_potential", "smoothstep", "blend_weight", "band_width", "BAND_MARGINS"]

BAND_MARGINS = 2.0  # the blend band is at least this many contact margins wide


def central_potential(r: torch.Tensor, *, mu: float = DEFAULT_CONTACT.stiffness) -> torch.Tensor:
    """Closed-form potential of two contracted clusters whose centres are ``r`` apart.

    Args:
        r: (...) centre distance [m], > 0. ``r = 0`` gives ``+inf``.
        mu: contact coefficient (stiffness scale).

    Returns:
        (...) ``12 mu (1 + 1/sqrt(r))^2``, differentiable to any order by autograd. Its limit for r -> inf is the
        constant ``12 mu``, but its derivative ``-12 mu (r^-3/2 + r^-2)`` never vanishes.

    Raises:
        TypeError: if ``r`` is not a tensor.
        ValueError: if ``r`` is not a floating tensor, holds NaN, or is negative, or ``mu`` is not a finite positive
            number.
    """
    check_finite_tensor(r, "r", allow_inf=True)
    check_stiffness(mu, "mu")
    _check_distance(r)
    return 12.0 * mu * (1.0 + torch.rsqrt(r)) ** 2


def smoothstep(s: torch.Tensor) -> torch.Tensor:
    """Quintic smoothstep ``Phi(s) = 6 s^5 - 15 s^4 + 10 s^3`` on [0, 1], clamped to 0 below and 1 above.

    ``Phi'(s) = 30 s^2 (s - 1)^2`` and ``Phi''(s) = 60 s (s - 1)(2 s - 1)`` vanish at both ends: C2 everywhere.

    Args:
        s: (...) blend coordinate.

    Returns:
        (...) Phi(s) in [0, 1], differentiable to any order (zero derivatives outside [0, 1]).

    Raises:
        TypeError: ``s`` is not a tensor.
        ValueError: ``s`` holds NaN or is not float32/float64.
    """
    check_finite_tensor(s, "s", allow_inf=True)
    t = s.clamp(0.0, 1.0)
    return t * t * t * (t * (6.0 * t - 15.0) + 10.0)


def band_width(d1: torch.Tensor | float, eps: float, margin: float = 0.0):
    """Width ``d2 - d1`` of the blend band of two nodes: ``max(eps d1, BAND_MARGINS margin)`` (module docstring)."""
    if isinstance(d1, torch.Tensor):
        return torch.clamp(eps * d1, min=BAND_MARGINS * margin)
    return max(eps * d1, BAND_MARGINS * margin)


def blend_weight(r: torch.Tensor, d1: torch.Tensor | float, eps: float, margin: float = 0.0) -> torch.Tensor:
    """Weight of the central potential in the blend of two nodes: ``Phi((r - d1) / w)``, ``w = band_width(d1, eps,
    margin) = max(eps d1, 2 margin)``.

    Args:
        r: (...) centre distance of the two nodes [m].
        d1: (...) or scalar, sum of the two bounding radii ``R_I + R_J`` [m], > 0.
        eps: relative width of the blend band, > 0 (``d2 = d1 + max(eps d1, 2 margin)``).
        margin: the contact margin delta [m] (the hierarchy's potential uses its own; 0: the band is ``eps d1``).

    Returns:
        (...) phi: 0 for r <= d1 (fine potential only), 1 for r >= d2 (central only; r = inf included), C2 in
        between.

    Raises:
        ValueError: eps not a finite positive number, margin negative, r NaN or negative, d1 not finite and > 0, or
            a d1 tensor of another dtype or device than r, or not broadcasting with it.
        TypeError: r not a tensor, or d1 neither a number nor a tensor.
    """
    check_positive(eps, "eps")
    if not (is_real(margin) and 0 <= margin < float("inf")):
        raise ValueError(f"margin must be a finite number >= 0, got {margin!r}")
    check_finite_tensor(r, "r", allow_inf=True)
    _check_distance(r)
    if not (isinstance(d1, torch.Tensor) or is_real(d1)):
        raise TypeError(f"d1 must be a number or a torch.Tensor, got {type(d1).__name__}")
    if isinstance(d1, torch.Tensor) and (d1.dtype != r.dtype or d1.device != r.device):
        raise ValueError(f"d1 is {d1.dtype} on {d1.device} but r is {r.dtype} on {r.device}: they must match")
    d1_t = torch.as_tensor(d1, dtype=r.dtype, device=r.device)
    try:
        torch.broadcast_shapes(r.shape, d1_t.shape)
    except RuntimeError:
        raise ValueError(
            f"d1 of shape {tuple(d1_t.shape)} does not broadcast with r of shape {tuple(r.shape)}"
        ) from None
    with outside_transforms():  # (values read from the plain tensors: the check runs under torch.func.vmap)
        if not bool((torch.isfinite(plain(d1_t)) & (plain(d1_t) > 0)).all()):
            raise ValueError(f"d1 must be finite and > 0 (a sum of two radii), got {plain(d1_t)}")
    w = band_width(d1, eps, margin)
    # beyond the band phi = 1 with zero derivatives: r is capped at d1 + 2 w, so that r = inf gives no inf - inf in
    # the derivatives with respect to d1
    cap = torch.as_tensor(d1 + 2.0 * w, dtype=r.dtype, device=r.device)
    return smoothstep((torch.minimum(r, cap) - d1) / w)


def _check_distance(r: torch.Tensor) -> None:
    """r >= 0, read from the plain tensor (so that the check runs under torch.func.vmap)."""
    with outside_transforms():
        neg = plain(r) < 0
        if bool(neg.any()):
            at = tuple(int(i) for i in torch.nonzero(neg)[0])
            raise ValueError(f"r must be >= 0 (a distance); first negative entry at index {at}")
