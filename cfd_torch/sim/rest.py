"""How high a body rests on a flat floor under its weight, and the contact stiffness for a chosen rest gap.

The potential is linear in its stiffness mu (every plane solve minimises mu E, whose minimiser does not depend on
mu), so the upward contact force on a body held a gap above a floor is mu F1(gap), F1 the force at mu = 1. At rest
that force carries the body's weight m g: the rest gap solves mu F1(gap) = m g, and the stiffness that rests the
body at a chosen gap is m g / F1(gap). The default stiffness suits bodies of decimetres and kilograms (about 1-2 mm
up); lighter and smaller bodies rest higher, centimetre ones centimetres up (:func:`rest_gap` tells how high).

The floor is a flat box three times the body's footprint under it (or the scene's own floor, ``floor=``), refined
as a :class:`cfd_torch.Scene` refines an obstacle for it (its ``refine_obstacles``), and the body keeps its mesh's
orientation (z up), its lowest vertex ``gap`` above the floor. The far field of a wider floor lifts a light body
further: a 2 cm, 8 g cube rests 6.0 mm above the default floor and 17 mm above a 1 m box at the default stiffness
(where a settled rollout rests it 15 mm up; a 5 cm, 125 g cube: 2.1, 2.65 and 2.65 mm).
"""

from __future__ import annotations

import math
import warnings

import torch
import trimesh

from .._validate import is_real
from ..config import ContactConfig
from ..contact.bsh import BSH
from ..contact.mesh import mesh_potential_derivatives
from .bodies import RigidBody, refine_obstacles, rigid_body

__all__ = ["RestGapWarning", "rest_gap", "stiffness_for_rest_gap"]

# a body is warned of when it would rest more than max(margin, this x its largest extent) above the margin
_HOVER_FRACTION = 0.05
_GRID = 40  # gaps scanned from the first the weight wins at down toward the margin (geometric)
_BISECTIONS = 60  # of the gap, between the grid's neighbours around the highest equilibrium


class RestGapWarning(UserWarning):
    """A dynamic body would rest far above its support at the scene's contact stiffness (see
    :func:`cfd_torch.rest_gap`)."""


def _check(body: object, gravity: object, contact: object, floor: object = None) -> ContactConfig:
    if not isinstance(body, RigidBody) or body.kind != "dynamic":
        raise TypeError(f"body must be a dynamic cfd_torch.RigidBody (rigid_body(mesh)), got {body!r:.80}")
    if floor is not None and not isinstance(floor, RigidBody):
        raise TypeError(
            f"floor must be a cfd_torch.RigidBody (rigid_body(mesh, kind=...)), got {floor!r:.80}"
        )
    if not (is_real(gravity) and 0 < float(gravity) < math.inf):
        raise ValueError(f"gravity must be a positive finite number [m/s^2], got {gravity!r}")
    if contact is None:
        return ContactConfig()
    if not isinstance(contact, ContactConfig) or contact.potential != "cfd":
        raise ValueError(
            f"contact must be a ContactConfig of this library's potential (cfd), got {contact!r}"
        )
    return contact


def _floor(body: RigidBody, contact: ContactConfig, floor: RigidBody | None = None) -> BSH:
    """The floor's hierarchy, its top (its highest vertex) at z = 0 and centred under the body, refined as a Scene
    would; by default a flat box three times the body's footprint."""
    v = body.bsh.vertices
    lo, hi = v.amin(0), v.amax(0)
    centre = [float(lo[0] + hi[0]) / 2, float(lo[1] + hi[1]) / 2]
    if floor is None:
        side = 3.0 * float((hi - lo)[:2].max())
        depth = max(float((hi - lo).max()), 2.0 * contact.margin)
        box = trimesh.creation.box(extents=(side, side, depth))
        box.apply_translation([*centre, -depth / 2])
        floor = rigid_body(box, kind="static")
    else:
        fv = floor.bsh.vertices
        top = [float(fv[:, 0].amin() + fv[:, 0].amax()) / 2, float(fv[:, 1].amin() + fv[:, 1].amax()) / 2]
        shift = torch.tensor(
            [centre[0] - top[0], centre[1] - top[1], -float(fv[:, 2].amax())], dtype=fv.dtype
        )
        floor = rigid_body(trimesh.Trimesh(fv + shift, floor.bsh.faces, process=False), kind="static")
    if contact.refine_obstacles is None:
        return floor.bsh
    pair = torch.tensor([[0, 1]], dtype=torch.long)
    with warnings.catch_warnings():  # a floor refined to fewer faces than asked: a scene warns of its own
        warnings.simplefilter("ignore", UserWarning)
        return refine_obstacles((body, floor), pair, contact.refine_obstacles)[1].bsh


def _lift(body: RigidBody, floor: BSH, gap: float, contact: ContactConfig) -> float:
    """The upward contact force [N] at stiffness 1 on the body with its lowest vertex ``gap`` above the floor."""
    z = gap - float(body.bsh.vertices[:, 2].min())
    pose = torch.tensor([0.0, 0.0, z, 0.0, 0.0, 0.0], dtype=torch.float64)
    d = mesh_potential_derivatives(
        body.bsh, pose, floor, torch.zeros(6, dtype=torch.float64), mu=1.0, margin=contact.margin,
        eps=contact.eps, split=contact.split, hessian=False, tol=contact.pair_tol, max_iter=contact.pair_max_iter,
    )  # fmt: skip
    return -float(d.grad[2])


def rest_gap(
    body: RigidBody,
    stiffness: float | None = None,
    *,
    floor: RigidBody | None = None,
    gravity: float = 9.81,
    contact: ContactConfig | None = None,
) -> float:
    """The gap [m] between a body's lowest vertex and a flat floor at which the contact force carries its weight.

    Args:
        body: a dynamic body (:func:`cfd_torch.rigid_body`), in its mesh's orientation.
        stiffness: the contact stiffness mu (default: ``contact``'s).
        floor: the floor to rest on (any :func:`cfd_torch.rigid_body`, its highest vertex taken as its top and its
            footprint's centre put under the body; a scene's own floor gives that scene's gap, its far field
            included: a wider floor pushes a light body up further); default: a flat box three times the body's
            footprint.
        gravity: the magnitude of gravity [m/s^2].
        contact: the contact settings (margin, blend width, obstacle refinement; default ``ContactConfig()``).

    Returns:
        The highest gap at which the force is the weight, to 1e-6 relative (above the margin, where the force grows
        without bound): a body placed higher falls to it. The lift is not monotone in the gap everywhere (the far
        field's blend bands), so there may be lower equilibria too; the highest is found on a geometric grid of 40
        gaps down toward the margin (a crossing narrower than the grid's spacing can be missed).

    Raises:
        TypeError, ValueError: a body that is not a dynamic RigidBody, a gravity or stiffness that is not a positive
            finite number, a contact config of a baseline potential.
    """
    contact = _check(body, gravity, contact, floor)
    mu = contact.stiffness if stiffness is None else stiffness
    if not (is_real(mu) and 0 < float(mu) < math.inf):
        raise ValueError(f"stiffness must be a positive finite number, got {stiffness!r}")
    bsh, weight = _floor(body, contact, floor), body.mass * float(gravity)
    size = float((body.bsh.vertices.amax(0) - body.bsh.vertices.amin(0)).max())
    hi = contact.margin + max(contact.margin, size)
    while float(mu) * _lift(body, bsh, hi, contact) > weight:  # bracket: the weight wins at hi
        hi *= 2.0
        if hi > 1e3 * size:
            raise ValueError(
                f"the contact force at stiffness {mu:g} outweighs this body's weight up to {hi:.3g} m above the "
                "floor (1,000 times its size): it does not rest"
            )
    # the lift need not fall monotonically with the gap (the far field's blend bands): the highest equilibrium is
    # found on a geometric grid from hi down toward the margin, then bisected
    lo = contact.margin * (1.0 + 1e-6)
    grid = [lo * (hi / lo) ** (k / _GRID) for k in range(_GRID, -1, -1)]
    for upper, lower in zip(grid, grid[1:], strict=False):
        if float(mu) * _lift(body, bsh, lower, contact) > weight:
            lo, hi = lower, upper
            break
    for _ in range(_BISECTIONS):
        mid = 0.5 * (lo + hi)
        if float(mu) * _lift(body, bsh, mid, contact) > weight:
            lo = mid
        else:
            hi = mid
        if hi - lo <= 1e-6 * hi:
            break
    return 0.5 * (lo + hi)


def stiffness_for_rest_gap(
    body: RigidBody,
    gap: float,
    *,
    floor: RigidBody | None = None,
    gravity: float = 9.81,
    contact: ContactConfig | None = None,
) -> float:
    """The contact stiffness mu at which a body rests ``gap`` [m] above a flat floor (its lowest vertex).

    Args:
        body, floor, gravity, contact: as in :func:`rest_gap` (``contact``'s stiffness is not read).
        gap: the rest gap wanted [m], above ``contact``'s margin.

    Raises:
        TypeError, ValueError: as :func:`rest_gap`; a gap that is not a finite number above the margin.
    """
    contact = _check(body, gravity, contact, floor)
    if not (is_real(gap) and contact.margin < float(gap) < math.inf):
        raise ValueError(
            f"gap must be a finite number above the contact margin {contact.margin:g} m, got {gap!r}"
        )
    return body.mass * float(gravity) / _lift(body, _floor(body, contact, floor), float(gap), contact)


def warn_hovering(bodies, contact: ContactConfig, gravity: tuple[float, float, float]) -> None:
    """Warn (:class:`RestGapWarning`) of each distinct dynamic body of ``bodies`` that would rest more than
    max(margin, 5 % of its largest extent) above the margin at ``contact``'s stiffness, on the default floor of
    :func:`rest_gap` (a lower bound of its gap on a wider floor), with a stiffness that rests it two margins up there.
    Nothing without gravity, with gravity not along -z, or for a baseline potential. One evaluation of the potential
    per distinct body."""
    g = math.sqrt(sum(x * x for x in gravity))
    # (the floor model is z up: gravity along another axis has the bodies rest on other faces than it assumes)
    if g == 0 or contact.potential != "cfd" or not -gravity[2] > (1 - 1e-9) * g:
        return
    seen: set[int] = set()
    for k, body in enumerate(bodies):
        if body.kind != "dynamic" or id(body) in seen:
            continue
        seen.add(id(body))
        size = float((body.bsh.vertices.amax(0) - body.bsh.vertices.amin(0)).max())
        allowed = contact.margin + max(contact.margin, _HOVER_FRACTION * size)
        floor = _floor(body, contact)
        if contact.stiffness * _lift(body, floor, allowed, contact) <= body.mass * g:
            continue
        try:
            gap = rest_gap(body, gravity=g, contact=contact)
            where = f"would rest about {1e3 * gap:.3g} mm above a floor three times its width (higher on a wider one)"
        except ValueError:  # the far field outweighs it at any gap
            where = "would be pushed off a flat floor to any height"
        better = body.mass * g / _lift(body, floor, 2.0 * contact.margin, contact)
        warnings.warn(
            f"body {k} ({body.mass:.3g} kg, {100 * size:.3g} cm across) {where} at the contact stiffness "
            f"mu={contact.stiffness:g} (its lowest vertex; the default suits bodies of decimetres and kilograms): "
            f"mu={better:.2g} rests it about {2e3 * contact.margin:.3g} mm up (cfd_torch.stiffness_for_rest_gap, "
            "cfd_torch.rest_gap)",
            RestGapWarning,
            stacklevel=3,
        )
