"""How high a body rests on a flat floor under its weight, and the contact stiffness for a chosen rest gap.

The potential is linear in its stiffness mu (every plane solve minimises mu E, whose minimiser does not depend on
mu), so the upward contact force on a body held a gap above a floor is mu F1(gap), F1 the force at mu = 1. At rest
that force carries the body's weight m g: the rest gap solves mu F1(gap) = m g, and the stiffness that rests the
body at a chosen gap is m g / F1(gap). The default stiffness suits bodies of decimetres and kilograms (about 1-2 mm
up); lighter and smaller bodies rest higher, centimetre ones centimetres up (:func:`rest_gap` tells how high).

The floor is a flat box three times the body's footprint under it (or the scene's own floor, ``floor=``), refined
as a :class:`cfd_torch.Scene` refines an obstacle for it (its ``refine_obstacles``), and the body keeps its mesh's
orientation (z up), its lowest vertex ``gap`` above the floor. The floor's extent and refinement move the gap: at
the default stiffness a 2 cm, 8 g cube rests 6.0 mm above the default floor and 12-17 mm above a 1 m box,
depending on where it is released (a settled rollout: 15 mm); a 5 cm, 125 g cube 2.1 and 2.65 mm (the rollout
2.65); a 0.5 kg ball of 5 cm radius 4.6 mm, and 3.1 mm above a 2 m box (the rollout 3.0).
"""

from __future__ import annotations

import dataclasses
import hashlib
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

# a body is warned of when it would rest more than max(margin, this x its height) above the margin
_HOVER_FRACTION = 0.05
# the geometric grid of gaps the released body moves along, down or up, to the first crossing
_GRID_RATIO = 1.1
_BISECTIONS = 60  # of the gap, between the grid's neighbours around that crossing


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
    mu: float | None = None,
    *,
    floor: RigidBody | None = None,
    start: float | None = None,
    gravity: float = 9.81,
    contact: ContactConfig | None = None,
) -> float:
    """The gap [m] between a body's lowest vertex and a flat floor where the body, released at rest ``start`` above
    it, comes to rest: the contact force carries its weight there and falls below it just above.

    Args:
        body: a dynamic body (:func:`cfd_torch.rigid_body`), in its mesh's orientation.
        mu: the contact stiffness (``ContactConfig.stiffness``, Scene's ``mu=``; default: ``contact``'s).
        floor: the floor to rest on (any :func:`cfd_torch.rigid_body`, its highest vertex taken as its top and its
            footprint's centre put under the body); default: a flat box three times the body's footprint. The
            floor's extent and refinement move the gap (far-field lift, and a wide floor refined more coarsely
            under the cap of ``MAX_REFINED_FACES``): pass the scene's own floor for that scene's gap.
        start: the gap it is released at [m] (default: the margin plus the larger of the margin and the body's
            height).
        gravity: the magnitude of gravity [m/s^2].
        contact: the contact settings (margin, blend width, obstacle refinement; default ``ContactConfig()``).

    Returns:
        The gap, to 1e-6 relative (above the margin, where the force grows without bound): from ``start`` the body
        moves down while its weight wins and up while the lift does, to the first gap where they change places
        (found on a geometric grid of ratio 1.1 from ``start``, then bisected; a swing narrower than the grid's
        spacing can be missed). Near contact the lift falls with the gap; farther out, the far field's blend
        bands make it rise and fall (a light body over a wide floor can balance at several heights), hence the
        release height.

    Raises:
        TypeError, ValueError: a body that is not a dynamic RigidBody, a gravity or mu that is not a positive finite
            number, a contact config of a baseline potential; a mu whose far field outweighs the body up to 1,000
            times its size (it does not rest).
    """
    contact = _check(body, gravity, contact, floor)
    given = mu
    mu = contact.stiffness if mu is None else mu
    if not (is_real(mu) and 0 < float(mu) < math.inf):
        raise ValueError(f"mu must be a positive finite number, got {given!r}")
    if start is None:
        start = _default_start(body, contact)
    if not (is_real(start) and contact.margin < float(start) < math.inf):
        raise ValueError(
            f"start must be a finite number above the contact margin {contact.margin:g} m, got {start!r}"
        )
    return _settle(
        body, _floor(body, contact, floor), float(mu), body.mass * float(gravity), float(start), contact
    )


def _default_start(body: RigidBody, contact: ContactConfig) -> float:
    """:func:`rest_gap`'s default release gap: the margin plus the larger of the margin and the body's height."""
    v = body.bsh.vertices[:, 2]
    return contact.margin + max(contact.margin, float(v.amax() - v.amin()))


def _settle(
    body: RigidBody, bsh: BSH, mu: float, weight: float, start: float, contact: ContactConfig
) -> float:
    """:func:`rest_gap` on the floor's hierarchy ``bsh``, its arguments checked."""
    v = body.bsh.vertices
    size = float((v.amax(0) - v.amin(0)).max())

    def lifts(gap: float) -> bool:
        return mu * _lift(body, bsh, gap, contact) > weight

    # (lo, hi): the lift wins at lo, the weight at hi, the two neighbours on the grid around the first crossing
    gap = start
    if lifts(gap):  # pushed up: to the first gap the weight wins at
        while True:
            up = gap * _GRID_RATIO
            if up > 1e3 * size:
                raise ValueError(
                    f"the contact force at mu {mu:g} outweighs this body's weight up to {up:.3g} m above the floor "
                    "(1,000 times its size): it does not rest"
                )
            if not lifts(up):
                lo, hi = gap, up
                break
            gap = up
    else:  # falls: to the first gap the lift wins at (it always does near the margin)
        while True:
            down = max(gap / _GRID_RATIO, contact.margin * (1.0 + 1e-9))
            if lifts(down) or down == gap:
                lo, hi = down, gap
                break
            gap = down
    for _ in range(_BISECTIONS):
        mid = 0.5 * (lo + hi)
        if lifts(mid):
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
    """The contact stiffness mu at which the lift on a body ``gap`` [m] above a flat floor (its lowest vertex) carries
    its weight.

    Args:
        body, floor, gravity, contact: as in :func:`rest_gap` (``contact``'s stiffness is not read).
        gap: the rest gap wanted [m], above ``contact``'s margin.

    Returns:
        mu: the body is in equilibrium at ``gap``. Where the lift grows with the gap there (the far field's blend
        bands) that equilibrium is unstable: a :class:`RestGapWarning` says so and where the body released just
        above it comes to rest.

    Raises:
        TypeError, ValueError: as :func:`rest_gap`; a gap that is not a finite number above the margin.
    """
    contact = _check(body, gravity, contact, floor)
    if not (is_real(gap) and contact.margin < float(gap) < math.inf):
        raise ValueError(
            f"gap must be a finite number above the contact margin {contact.margin:g} m, got {gap!r}"
        )
    bsh, weight = _floor(body, contact, floor), body.mass * float(gravity)
    mu = weight / _lift(body, bsh, float(gap), contact)
    above = float(gap) * (1 + 1e-3)
    if mu * _lift(body, bsh, above, contact) > weight:  # the lift grows with the gap there
        ends = _settle(body, bsh, mu, weight, above, contact)
        warnings.warn(
            f"at mu={mu:.6g} the body balances {1e3 * float(gap):.4g} mm above the floor, but unstably (the lift "
            f"grows with the gap there): released just above it, it rests at {1e3 * ends:.4g} mm",
            RestGapWarning,
            stacklevel=2,
        )
    return mu


def warn_hovering(
    bodies,
    contact: ContactConfig,
    gravity: tuple[float, float, float],
    planar: bool = False,
    pair_mu: dict[tuple[int, int], float] | None = None,
) -> None:
    """Warn (:class:`RestGapWarning`, once per shape) of the dynamic bodies of ``bodies`` that would rest more than
    max(margin, 5 % of their height) above the margin at their stiffness, on the default floor of
    :func:`rest_gap`, naming a stiffness that rests them two margins up there. A body's stiffness is the least of
    its pairs' with the static bodies (with the kinematic ones in a scene without a static body; ``pair_mu``'s,
    else ``contact``'s). Nothing in a planar scene (its
    heights are held), without a static or kinematic body to rest on, with gravity more than about 25 degrees off
    -z (the floor model is z up; the load is the weight along z), or for a baseline potential. Verdicts are kept
    per shape, mass and settings (one evaluation of the potential per new one; the whole search for the gap where
    it warns)."""
    g = -float(gravity[2])
    if planar or contact.potential != "cfd" or not g > 0.9 * math.sqrt(sum(x * x for x in gravity)):
        return
    if all(b.kind == "dynamic" for b in bodies):
        return
    pair_mu = pair_mu or {}
    # what a body rests on: the static bodies (the kinematic ones where there is none, e.g. a moving platform)
    supports = [j for j, b in enumerate(bodies) if b.kind == "static"] or [
        j for j, b in enumerate(bodies) if b.kind == "kinematic"
    ]
    rows: dict[tuple, list[int]] = {}  # each verdict's bodies, in order
    for k, body in enumerate(bodies):
        if body.kind != "dynamic":
            continue
        mu = min(pair_mu.get((k, j), pair_mu.get((j, k), contact.stiffness)) for j in supports)
        own = contact if mu == contact.stiffness else dataclasses.replace(contact, stiffness=mu)
        key = (_shape_key(body.bsh), body.mass, own, g)
        if key not in _VERDICTS:
            if len(_VERDICTS) >= _MAX_VERDICTS:
                _VERDICTS.pop(next(iter(_VERDICTS)))
            _VERDICTS[key] = _verdict(body, own, g)
        rows.setdefault(key, []).append(k)
    for key, ks in rows.items():
        if _VERDICTS[key] is not None:
            who = f"body {ks[0]}" if len(ks) == 1 else f"bodies {', '.join(map(str, ks))}"
            warnings.warn(f"{who} {_VERDICTS[key]}", RestGapWarning, stacklevel=3)


_MAX_VERDICTS = 1024
_VERDICTS: dict[tuple, str | None] = {}  # memo: (shape, mass, contact settings, load) -> message or None


def _shape_key(bsh: BSH) -> bytes:
    """A digest of a hierarchy's vertices and faces (bodies of one shape built separately share verdicts)."""
    h = hashlib.blake2b(digest_size=16)
    h.update(bsh.vertices.numpy().tobytes())
    h.update(bsh.faces.numpy().tobytes())
    return h.digest()


def _verdict(body: RigidBody, contact: ContactConfig, g: float) -> str | None:
    """The warning's text (after "body k ") if the body would rest too high, else None."""
    v = body.bsh.vertices
    height = float(v[:, 2].amax() - v[:, 2].amin())
    allowed = contact.margin + max(contact.margin, _HOVER_FRACTION * height)
    floor = _floor(body, contact)
    if contact.stiffness * _lift(body, floor, allowed, contact) <= body.mass * g:
        return None
    try:
        gap = _settle(body, floor, contact.stiffness, body.mass * g, _default_start(body, contact), contact)
        where = f"would rest about {1e3 * gap:.3g} mm above a floor three times its width"
    except ValueError:  # the far field outweighs it at any gap
        where = "would be pushed off a flat floor to any height"
    better = body.mass * g / _lift(body, floor, 2.0 * contact.margin, contact)
    return (
        f"({body.mass:.3g} kg, {100 * height:.3g} cm tall) {where} at the contact stiffness mu={contact.stiffness:g} "
        f"(its lowest vertex; the default suits bodies of decimetres and kilograms): mu={better:.2g} rests it about "
        f"{2e3 * contact.margin:.3g} mm up there (Scene(..., pair_mu={{(body, floor): mu}}) for its contacts alone; "
        "cfd_torch.rest_gap(body, mu, floor=...) for a given floor, cfd_torch.stiffness_for_rest_gap)"
    )
