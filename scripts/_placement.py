"""Placing a ball on an arbitrary obstacle mesh (shared by the benchmark scripts' ``--obstacle`` cases)."""

from __future__ import annotations

import numpy as np
import trimesh


def load_obstacle(path: str) -> trimesh.Trimesh:
    """The triangle mesh in the file ``path`` (any format trimesh reads; a scene's meshes are concatenated)."""
    try:
        mesh = trimesh.load(path, force="mesh")
    except (NotImplementedError, ValueError) as err:  # (a format trimesh does not know, e.g. no extension)
        raise ValueError(f"--obstacle: trimesh cannot read {path}: {err}") from None
    if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0:
        raise ValueError(f"--obstacle: {path} holds no triangle mesh")
    return mesh


def surface_heights(mesh: trimesh.Trimesh, xy: np.ndarray) -> np.ndarray:
    """(P,) the highest point of ``mesh``'s surface straight above or below each point ``xy`` (P, 2), -inf where no
    triangle covers it (vertical rays, tested against every triangle whose xy bounds hold the point)."""
    tri = np.asarray(mesh.triangles, dtype=np.float64)  # (F, 3, 3)
    lo, hi = tri[:, :, :2].min(1), tri[:, :, :2].max(1)
    out = np.full(len(xy), -np.inf)
    for i, p in enumerate(np.asarray(xy, dtype=np.float64)):
        t = tri[np.all((lo <= p) & (p <= hi), axis=1)]
        if len(t) == 0:
            continue
        a, b, c = t[:, 0], t[:, 1], t[:, 2]
        e1, e2, w = b[:, :2] - a[:, :2], c[:, :2] - a[:, :2], p - a[:, :2]
        det = e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]
        ok = np.abs(det) > 1e-14 * (np.abs(e1).sum(1) * np.abs(e2).sum(1) + 1e-300)  # not seen edge-on
        det = np.where(ok, det, 1.0)
        u = (w[:, 0] * e2[:, 1] - w[:, 1] * e2[:, 0]) / det
        v = (e1[:, 0] * w[:, 1] - e1[:, 1] * w[:, 0]) / det
        inside = ok & (u >= -1e-12) & (v >= -1e-12) & (u + v <= 1 + 1e-12)
        if inside.any():
            z = a[:, 2] + u * (b[:, 2] - a[:, 2]) + v * (c[:, 2] - a[:, 2])
            out[i] = z[inside].max()
    return out


def rest_height(
    obstacle: trimesh.Trimesh, radius: float, xy: tuple[float, float], gap: float, n: int = 21
) -> float:
    """The height of the centre of a ball of ``radius`` (a mesh inscribed in that sphere, like an icosphere) at
    ``xy`` whose surface is at least ``gap`` above ``obstacle``'s surface at an n x n grid of points over its
    footprint: max over the points at horizontal distance rho of (surface height + sqrt(radius^2 - rho^2)) + gap.
    Raises ValueError when the obstacle does not lie under the ball's centre."""
    s = np.linspace(-radius, radius, n)
    gx, gy = np.meshgrid(s, s)
    rho2 = gx.ravel() ** 2 + gy.ravel() ** 2
    keep = rho2 <= radius**2
    pts = np.stack([gx.ravel()[keep] + xy[0], gy.ravel()[keep] + xy[1]], 1)
    h = surface_heights(obstacle, pts)
    if not np.isfinite(surface_heights(obstacle, np.asarray([xy]))[0]):
        raise ValueError(f"--obstacle: no part of the obstacle lies under the ball's centre {tuple(xy)}")
    need = h + np.sqrt(radius**2 - rho2[keep])  # the centre's height that puts the sphere on each point
    return float(need[np.isfinite(need)].max()) + gap


def ball_over(obstacle: trimesh.Trimesh, radius: float, gap: float) -> tuple[float, float, float]:
    """The benchmarks' ball position over ``obstacle``: centred over its xy bounds offset by (0.08, 0.04) of their
    extents (off any symmetry line), or, where no part of the obstacle lies under that point (a ring's hole, the
    notch of an L), over the centroid of the non-vertical triangle nearest to it; its surface ``gap`` above the
    obstacle's surface (:func:`rest_height`). Raises ValueError when every triangle is vertical."""
    (x0, y0, _), (x1, y1, _) = obstacle.bounds
    xy = np.array([0.5 * (x0 + x1) + 0.08 * (x1 - x0), 0.5 * (y0 + y1) + 0.04 * (y1 - y0)])
    if not np.isfinite(surface_heights(obstacle, xy[None])[0]):
        tri = np.asarray(obstacle.triangles, dtype=np.float64)
        e1, e2 = tri[:, 1, :2] - tri[:, 0, :2], tri[:, 2, :2] - tri[:, 0, :2]
        area = np.abs(e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0])  # twice the projected area
        seen = area > 1e-9 * max(float(area.max(initial=0.0)), 1e-300)
        if not seen.any():
            raise ValueError(
                "--obstacle: every triangle of the obstacle is vertical: nothing to rest a ball on"
            )
        centre = tri[seen, :, :2].mean(1)
        xy = centre[np.argmin(((centre - xy) ** 2).sum(1))]
    xy = (float(xy[0]), float(xy[1]))
    return (*xy, rest_height(obstacle, radius, xy, gap))
