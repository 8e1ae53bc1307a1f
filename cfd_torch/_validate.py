"""Input checks shared by the public functions: each raises a ``ValueError`` naming the argument and the first
offending batch index. Values are read from the plain tensor under torch.func wrappers (see ``_autograd.plain``), so
the checks run unchanged under ``torch.func.grad``. Meshes given as arrays (bodies, hierarchies) have their own
checks, run once when a body is built: :func:`check_mesh` and :func:`self_intersection`."""

from __future__ import annotations

import functools
import math
from collections.abc import Mapping

import numba
import numpy as np
import torch

from ._autograd import legacy_batched, outside_transforms, plain
from ._geometry import segment_hits_triangle_nb, tri_tri_closest_nb
from ._threads import parallel_kernels, serial_twin, start_numba_pool

# A triangle is degenerate when twice its area is below this many machine epsilons of its longest edge squared
# (scale-free: a tiny well-shaped triangle is valid, a needle or a collinear triple is not).
_DEGENERACY_EPS_MULTIPLE = 100.0
FLOATS = (torch.float32, torch.float64)  # the dtypes the public entry points take


# largest coordinate magnitude of a triangle [m]: the pair solve converges for unit triangles up to 1e32 m apart,
# not from about 1e35 (its tests cannot resolve what is left), and squared distances overflow float64 from 1e154
_MAX_COORD = 1e30
# float32 inputs (solved in float64, derivatives rounded to float32): a unit pair's Hessian underflows float32 from
# about 1e16 m apart and its gradient from 1e25, so their coordinates stop well short of that
_MAX_COORD_FLOAT32 = 1e12


def narrowed(x: torch.Tensor, dtype: torch.dtype, what: str, inputs: str) -> torch.Tensor:
    """``x`` (a float64 result) cast to the inputs' ``dtype``: a ValueError if a finite entry overflows it (with a
    huge stiffness, or tiny triangles nearly at the margin), which would read as +inf (infeasible) or poison a solve.
    ``what`` names the result, ``inputs`` the arguments whose dtype it takes."""
    y = x.to(dtype)
    if dtype != x.dtype:
        if legacy_batched(x):  # (its values cannot be read: no check possible)
            raise NotImplementedError(
                f"{what} in {dtype}: autograd's batched gradients (torch.autograd.functional.jacobian or hessian "
                f"with vectorize=True, autograd.grad with is_grads_batched=True) cannot check its cast from float64 "
                f"for overflow; pass {inputs} as float64, or use vectorize=False"
            )
        with outside_transforms():
            px = plain(x).detach()
            over = torch.isfinite(px) & ~torch.isfinite(plain(y))
            if bool(over.any()):
                raise ValueError(
                    f"{what} overflows {dtype} ({float(px[over].abs().max()):.3g} > {torch.finfo(dtype).max:.3g}; the "
                    f"solve runs in float64): pass {inputs} as float64"
                )
    return y


class _Widen(torch.autograd.Function):
    """x cast to float64, whose backward casts the gradient back to x's dtype through :func:`narrowed` (a gradient
    that overflows it raises instead of reading as inf; under create_graph the Hessian-vector products come back
    through the same backward, so they are checked too)."""

    generate_vmap_rule = True

    @staticmethod
    def forward(x: torch.Tensor, what: str, inputs: str) -> torch.Tensor:
        return x.to(torch.float64)

    @staticmethod
    def setup_context(ctx, inputs, output):
        x, ctx.what, ctx.inputs = inputs
        ctx.dtype = x.dtype

    @staticmethod
    def backward(ctx, g: torch.Tensor) -> tuple[torch.Tensor, None, None]:
        return narrowed(g, ctx.dtype, f"{ctx.what}'s gradient", ctx.inputs), None, None

    @staticmethod
    def jvp(ctx, x_t: torch.Tensor, *_) -> torch.Tensor:
        # (the tangent passes on widened, to the potential's own Function, which refuses forward mode by name)
        return x_t.to(torch.float64)


def widened(x: torch.Tensor, what: str, inputs: str) -> torch.Tensor:
    """``x`` in float64 for a solve; where it is narrower, derivatives flowing back to it are cast back to its
    dtype by :func:`narrowed` (``what`` names the function, ``inputs`` the arguments, as there)."""
    if x.dtype == torch.float64:
        return x
    return _Widen.apply(x, what, inputs)


# why a pose's translation is limited (the messages of the pose checks)
FAR = (
    "the limit pair_potential puts on coordinates of this dtype (float64: from about 1e154 m the spheres' squared "
    "distances overflow and the gradient rounds to zero; float32: its derivatives underflow from about 1e16 m)"
)


# the longest rotation vector a pose may hold [rad]: its float64 spacing there, 1.2e-10 rad, is about a step's
# newton_tol (a step solves from the re-centred rotation, the same one to that spacing)
MAX_ROTATION = 1e6


def check_rotation_length(
    pose: torch.Tensor,
    name: str,
    where,
    advice: str = "wrap it to the same rotation (cfd_torch.recentre_rotation)",
) -> None:
    """A ValueError naming ``name`` and ``where(mask)`` (the first offending pose of the (...,) mask) if some pose
    of ``pose`` (..., 6) has a rotation vector longer than :data:`MAX_ROTATION`; ``advice`` ends the message."""
    with outside_transforms():
        turns = plain(pose).detach()[..., 3:].norm(dim=-1) > MAX_ROTATION
    if bool(turns.any()):
        raise ValueError(
            f"{name} has a rotation vector longer than {MAX_ROTATION:g} rad (first at {where(turns)}): beyond 1e6 "
            "rad the float64 spacing of a rotation vector exceeds 1.2e-10 rad (about a step's newton_tol), too "
            f"coarse to say which rotation it is; {advice}"
        )


def check_translation_range(pose: torch.Tensor, name: str, where, limit: float) -> None:
    """A ValueError naming ``name`` and ``where(mask)`` (the first offending pose of the (...,) mask) if some pose
    of ``pose`` (..., 6) has a translation coordinate beyond ``limit`` [m] in magnitude (:func:`max_coord`)."""
    with outside_transforms():
        far = plain(pose).detach()[..., :3].abs().amax(-1) > limit
    if bool(far.any()):
        raise ValueError(f"{name} has a translation beyond {limit:g} m (first at {where(far)}): {FAR}")


def check_bool(x: object, name: str) -> None:
    """A TypeError naming ``name`` unless ``x`` is a Python bool (a string such as "no" would read as True)."""
    if not isinstance(x, bool):
        raise TypeError(f"{name} must be a bool, got {x!r}")


def check_alike(a: torch.Tensor, b: torch.Tensor, name_a: str, name_b: str) -> None:
    """A ValueError naming both unless the tensors ``a`` and ``b`` share a dtype and a device."""
    if a.dtype != b.dtype:
        raise ValueError(f"{name_a} and {name_b} must share a dtype, got {a.dtype} and {b.dtype}")
    if a.device != b.device:
        raise ValueError(f"{name_a} and {name_b} must be on one device, got {a.device} and {b.device}")


def max_coord(dtype: torch.dtype) -> float:
    """The largest coordinate magnitude [m] the contact functions take in ``dtype``."""
    return _MAX_COORD_FLOAT32 if dtype == torch.float32 else _MAX_COORD


def _index_str(mask: torch.Tensor) -> str:
    idx = torch.nonzero(mask)[0]
    return "(" + ", ".join(str(int(i)) for i in idx) + ")"


def check_dense(x: torch.Tensor, name: str) -> None:
    """A TypeError naming ``name`` unless ``x`` is a dense (strided) tensor: sparse and other layouts failed deep
    inside torch, with messages that named none of the caller's arguments."""
    if x.layout != torch.strided:
        raise TypeError(f"{name} must be a dense (strided) tensor, got layout {x.layout}")


def check_finite_tensor(x: object, name: str, *, allow_inf: bool = False) -> None:
    """Require a floating-point tensor without NaN (and without inf unless ``allow_inf``)."""
    if not isinstance(x, torch.Tensor):
        raise TypeError(f"{name} must be a torch.Tensor, got {type(x).__name__}")
    check_dense(x, name)
    if x.dtype not in FLOATS:
        raise ValueError(f"{name} must have a floating dtype (float32 or float64), got {x.dtype}")
    with outside_transforms():
        x = plain(x)
        bad = torch.isnan(x) if allow_inf else ~torch.isfinite(x)
        if bool(bad.any()):
            what = "NaN" if allow_inf else "NaN or inf"
            raise ValueError(
                f"{name} contains {what} (first at index {_index_str(bad)}, {int(bad.sum())} entries)"
            )


def usable_device(device: torch.device | str, name: str = "device") -> torch.device:
    """``device`` as a torch.device that holds data in this torch build (not 'meta', not a backend it was built
    without or whose device is absent), else a ValueError naming ``name``."""
    try:
        dev = torch.device(device)
        torch.empty(0, device=dev)
    except (RuntimeError, AssertionError, TypeError) as e:
        raise ValueError(f"{name} {device!r} is not usable with this torch build: {e}") from e
    if dev.type == "meta":
        raise ValueError(f"{name} 'meta' holds no data: a device that computes is needed (cpu, cuda)")
    return dev


def check_not_meta(x: torch.Tensor, name: str) -> None:
    """Refuse a tensor on the 'meta' device (a shape without values), naming it."""
    if x.device.type == "meta":
        raise ValueError(
            f"{name} is on the 'meta' device (shapes without data): the potential needs its values"
        )


def check_triangles(tri: object, name: str) -> None:
    """Validate a ``(..., 3, 3)`` batch of triangles: dtype, shape, finiteness and non-degeneracy.

    Args:
        tri: (..., 3, 3) vertices (vertex index, then xyz).
        name: argument name used in error messages.
    """
    if not isinstance(tri, torch.Tensor):
        raise TypeError(f"{name} must be a torch.Tensor, got {type(tri).__name__}")
    check_dense(tri, name)
    check_not_meta(tri, name)
    if tri.dim() < 2 or tri.shape[-2:] != (3, 3):
        raise ValueError(f"{name} must have shape (..., 3, 3) (three vertices, xyz), got {tuple(tri.shape)}")
    if tri.dtype not in (torch.float32, torch.float64):
        raise ValueError(f"{name} must be float32 or float64, got {tri.dtype}")
    # the solve's precision (float64, on the float32 values exactly): a thin float32 triangle is as valid as in float64
    tol = _DEGENERACY_EPS_MULTIPLE * torch.finfo(torch.float64).eps
    with outside_transforms():
        _check_triangle_values(plain(tri), name, tol, max_coord(tri.dtype))


def _eager(fn):
    """``fn`` run eagerly under torch.compile (outside its graph). ``torch.compiler.disable`` imports dynamo, which
    would add about 1.3 s to every ``import cfd_torch``: the disabled twin is made at the first call that dynamo
    traces (where it is imported already)."""
    disabled = []

    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        if not torch.compiler.is_compiling():
            return fn(*args, **kwargs)
        if not disabled:
            disabled.append(torch.compiler.disable(fn))
        return disabled[0](*args, **kwargs)

    return wrapper


# torch.compile: dynamo cannot trace numba's first-call compilation (it fails on its bytecode), so this runs eagerly
@_eager
def _check_triangle_values(tri: torch.Tensor, name: str, tol: float, limit: float) -> None:
    if tri.device.type == "cpu":  # one fused pass (the tensor form below makes ~20 passes over the data)
        flat = tri.detach().reshape(-1, 3, 3).contiguous()
        code = torch.empty(flat.shape[0], dtype=torch.uint8)
        kernel = (
            _triangle_codes_nb if flat.shape[0] >= 100_000 and parallel_kernels() else _triangle_codes_serial
        )
        if kernel is _triangle_codes_nb:
            start_numba_pool()
        kernel(flat.numpy(), float(tol), float(limit), code.numpy())
        code = code.reshape(tri.shape[:-2])
        nonfinite, degenerate, huge = code == 1, code == 2, code == 3
    else:
        huge = tri.abs().flatten(-2).amax(-1) > limit
        e1 = tri[..., 1, :] - tri[..., 0, :]
        e2 = tri[..., 2, :] - tri[..., 0, :]
        e3 = tri[..., 2, :] - tri[..., 1, :]
        area2_sq = (torch.linalg.cross(e1, e2) ** 2).sum(-1)  # (2 area)^2
        longest_sq = torch.maximum(torch.maximum((e1 * e1).sum(-1), (e2 * e2).sum(-1)), (e3 * e3).sum(-1))
        degenerate = ~(area2_sq > (tol * longest_sq) ** 2)  # also True for coincident vertices and for NaN
        if not bool(degenerate.any() | huge.any()):
            return
        nonfinite = ~torch.isfinite(tri).flatten(-2).all(-1)
    if bool(nonfinite.any()):
        raise ValueError(
            f"{name} contains NaN or inf coordinates (triangle at batch index {_index_str(nonfinite)}, "
            f"{int(nonfinite.sum())} triangles)"
        )
    if bool(huge.any()):
        raise ValueError(
            f"{name} has coordinates beyond {limit:g} in magnitude, where the pair solve cannot resolve the "
            f"potential{' in float32' if tri.dtype == torch.float32 else ''} (triangle at batch index "
            f"{_index_str(huge)}, {int(huge.sum())} triangles)"
        )
    if bool(degenerate.any()):
        raise ValueError(
            f"{name} has degenerate triangles (collinear or coincident vertices relative to the triangle's size), "
            f"first at batch index {_index_str(degenerate)}, {int(degenerate.sum())} in all"
        )


@numba.njit(parallel=True, cache=True, error_model="numpy")
def _triangle_codes_nb(tri, tol, limit, code):
    """code[k] = 1 if triangle k has a NaN/inf coordinate, 3 if one beyond ``limit`` in magnitude, 2 if 2 area <=
    tol * longest edge^2, else 0."""
    for k in numba.prange(tri.shape[0]):
        t = tri[k]
        finite = True
        big = 0.0
        for i in range(3):
            for j in range(3):
                if not math.isfinite(t[i, j]):
                    finite = False
                big = max(big, abs(t[i, j]))
        if not finite:
            code[k] = 1
            continue
        if big > limit:
            code[k] = 3
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


def is_real(value: object) -> bool:
    """A real number (Python's or NumPy's), not a bool."""
    return isinstance(value, (int, float, np.integer, np.floating)) and not isinstance(
        value, (bool, np.bool_)
    )


def is_int(value: object) -> bool:
    """An integer (Python's or NumPy's, or a 0-d integer tensor), not a bool."""
    if isinstance(value, torch.Tensor):
        return value.dim() == 0 and not value.is_floating_point() and value.dtype not in (torch.bool,)
    return isinstance(value, (int, np.integer)) and not isinstance(value, (bool, np.bool_))


def check_positive(value: float, name: str) -> None:
    if not (is_real(value) and 0 < value < float("inf")):
        raise ValueError(f"{name} must be a finite positive number (int or float), got {value!r}")


# the largest contact stiffness mu: a unit triangle pair's E is about 13 / (gap - margin) near the margin (1.3e11 at
# 1e-10 m above it), and a feasible gap stays above the margin by its relative tolerance, so mu E keeps tens of orders
# of magnitude below float64's 1.8e308 (mu = 1e308 overflowed to +inf, which reads as penetration)
MAX_STIFFNESS = 1e250


def check_stiffness(value: float, name: str) -> None:
    """A contact stiffness mu: finite, positive and at most :data:`MAX_STIFFNESS`."""
    check_positive(value, name)
    if value > MAX_STIFFNESS:
        raise ValueError(
            f"{name} must be at most {MAX_STIFFNESS:g} (beyond, the potential's terms can overflow float64 and read "
            f"as penetration), got {value!r}"
        )


def check_tolerance(value: float, name: str) -> None:
    """A relative tolerance: a number in (0, 1)."""
    if not (is_real(value) and 0 < value < 1):
        raise ValueError(
            f"{name} must be a finite positive number below 1 (a relative tolerance), got {value!r}"
        )


def check_count(value: int, name: str, most: int = 10**6) -> None:
    """A positive int of at most ``most`` (an iteration cap: more is never meant, and the kernels take it as an
    int64 loop bound)."""
    if not (is_int(value) and 0 < value <= most):
        raise ValueError(f"{name} must be a positive int of at most {most:,}, got {value!r}")


_triangle_codes_serial = serial_twin(_triangle_codes_nb, cache=True, error_model="numpy")


def body_pair(p: object, name: str) -> tuple[int, int]:
    """A body pair (i, j) of integers (a tuple, list, or a row of an integer array or tensor), as given in ``name``."""
    try:
        ij = list(p)
    except TypeError:
        ij = []
    if not (len(ij) == 2 and all(is_int(x) for x in ij)):
        raise ValueError(f"{name} must hold body pairs (i, j) of integers, got {p!r}")
    return int(ij[0]), int(ij[1])


def check_pair_eps(pair_eps: object, n: int) -> dict[tuple[int, int], float]:
    """``pair_eps`` checked: body pairs of two different indices in [0, n), each with one positive blend width
    ((i, j) and (j, i) are one pair: given both, they must agree)."""
    return _pair_setting(pair_eps, n, "pair_eps", "eps", "the blend width", check_positive)


def check_pair_mu(pair_mu: object, n: int) -> dict[tuple[int, int], float]:
    """``pair_mu`` checked: body pairs of two different indices in [0, n), each with one contact stiffness (finite,
    positive, at most :data:`MAX_STIFFNESS`; (i, j) and (j, i) are one pair: given both, they must agree)."""
    return _pair_setting(pair_mu, n, "pair_mu", "mu", "the stiffness", check_stiffness)


def _pair_setting(
    value: object, n: int, name: str, short: str, what: str, check
) -> dict[tuple[int, int], float]:
    """A mapping {(i, j): x} of body pairs to one number each, checked (``check(x, label)`` raises ValueError)."""
    if value is None:
        return {}
    if not isinstance(value, Mapping):
        raise TypeError(f"{name} must be a mapping {{(i, j): {short}}}, got {type(value).__name__}")
    out: dict[tuple[int, int], float] = {}
    for key, x in value.items():
        i, j = body_pair(key, name)
        if not (0 <= i < n and 0 <= j < n and i != j):
            raise ValueError(f"{name}: {key!r} is not a pair of two body indices in [0, {n})")
        check(x, f"{name}: {what} of {key!r}")
        other = out.get((j, i))
        if other is not None and not math.isclose(other, float(x), rel_tol=1e-6):
            raise ValueError(f"{name}: {(i, j)} and {(j, i)} are one pair, given {float(x)} and {other}")
        out[(i, j)] = float(x)
    return out


def check_mesh(vertices: np.ndarray, faces: np.ndarray, vname: str, fname: str) -> None:
    """Validate a triangle mesh given as arrays: finite vertices, face indices in range, no degenerate face.

    Args:
        vertices: (V, 3) float64 vertex positions.
        faces: (F, 3) integer vertex indices.
        vname, fname: how the two are named in error messages (e.g. "mesh.vertices", "mesh.faces").
    """
    bad = ~np.isfinite(vertices).all(1)
    if bad.any():
        raise ValueError(
            f"{vname} contain NaN or inf (first at vertex {int(np.argmax(bad))}, {int(bad.sum())} in all)"
        )
    if faces.size and (faces.min() < 0 or faces.max() >= vertices.shape[0]):
        raise ValueError(f"{fname} index vertices out of range [0, {vertices.shape[0]})")
    tri = np.ascontiguousarray(vertices[faces], dtype=np.float64)  # (F, 3, 3)
    code = np.empty(tri.shape[0], dtype=np.uint8)
    kernel = _triangle_codes_nb if tri.shape[0] >= 100_000 and parallel_kernels() else _triangle_codes_serial
    if kernel is _triangle_codes_nb:
        start_numba_pool()
    kernel(tri, _DEGENERACY_EPS_MULTIPLE * float(np.finfo(np.float64).eps), _MAX_COORD, code)
    huge = code == 3
    if huge.any():
        raise ValueError(
            f"{vname} hold coordinates beyond {_MAX_COORD:g} in magnitude (first in face {int(np.argmax(huge))}, "
            f"{int(huge.sum())} faces in all), where the pair solve cannot resolve the potential"
        )
    bad = code != 0
    if bad.any():
        raise ValueError(
            f"{fname} has degenerate triangles (zero area: collinear or coincident vertices relative to the "
            f"triangle's size): first face {int(np.argmax(bad))}, {int(bad.sum())} in all"
        )


# Self-intersection: two faces that share no vertex meet when their distance is at most this fraction of the
# longer one's longest edge, or when an edge of one pierces the other at a sine of angle above it (an edge nearly
# parallel to the other face that pierces it comes within that distance of it anyway, and rounding cannot fake a
# crossing at a larger angle). Rounding of the distance is ~1e-16 of the pair's size, 7 orders below.
_TOUCH_REL = 1e-9


def closed_surface(vertices: np.ndarray, faces: np.ndarray) -> bool:
    """Whether the triangles (vertices welded by position) form closed, consistently wound surfaces: every directed
    edge occurs once and its reverse once (their winding number is then an integer away from them)."""
    _, weld = np.unique(np.asarray(vertices), axis=0, return_inverse=True)
    f = weld.reshape(-1)[np.asarray(faces)]
    e = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
    n = int(f.max()) + 1
    fwd = e[:, 0] * n + e[:, 1]
    rev = e[:, 1] * n + e[:, 0]
    fwd_sorted = np.sort(fwd)
    if len(fwd_sorted) > 1 and bool((fwd_sorted[1:] == fwd_sorted[:-1]).any()):
        return False
    return bool(np.isin(rev, fwd_sorted, assume_unique=False).all())


def winding_numbers(points: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """(P,) generalised winding numbers of the closed surface ``triangles`` (T, 3, 3) at ``points`` (P, 3): the
    summed signed solid angles of the triangles over 4 pi (Van Oosterom and Strackee), an integer (1 inside an
    outward-wound closed surface, 0 outside) away from the surface."""
    a = triangles[None, :, 0] - points[:, None]
    b = triangles[None, :, 1] - points[:, None]
    c = triangles[None, :, 2] - points[:, None]
    la, lb, lc = (np.linalg.norm(x, axis=-1) for x in (a, b, c))
    det = np.einsum("ptk,ptk->pt", a, np.cross(b, c))
    den = (
        la * lb * lc
        + np.einsum("ptk,ptk->pt", a, b) * lc
        + np.einsum("ptk,ptk->pt", b, c) * la
        + np.einsum("ptk,ptk->pt", c, a) * lb
    )
    return (2.0 * np.arctan2(det, den)).sum(1) / (4.0 * np.pi)


def miscounted_component(
    vertices: np.ndarray, faces: np.ndarray, labels: np.ndarray
) -> tuple[int, bool] | None:
    """A connected component (``labels`` (F,): each face's) of a closed, consistently wound, self-intersection-free
    mesh whose solid the volume integrals miscount, and whether it faces inward: an outward-wound one inside another
    (its solid counted twice), or an inward-wound one (a cavity) inside no outward one (its solid counted negative);
    None if there is none. Tested at a point just behind each component's largest face, where the whole mesh's
    winding number must be 1."""
    tri = vertices[faces]
    cross = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    area2 = np.linalg.norm(cross, axis=1)
    comps = np.unique(labels)
    lo = np.array([tri[labels == k].reshape(-1, 3).min(0) for k in comps])
    hi = np.array([tri[labels == k].reshape(-1, 3).max(0) for k in comps])
    # signed volume of each component (negative: wound inward)
    volume = np.bincount(labels, weights=np.einsum("ij,ij->i", tri[:, 0], cross) / 6.0)[comps]
    # an outward component can lie inside another only within its bounding box: test those, and every inward one
    within = ((lo[:, None] >= lo[None]) & (hi[:, None] <= hi[None])).all(2)
    np.fill_diagonal(within, False)
    cand = np.flatnonzero(within.any(1) | (volume < 0))
    if len(cand) == 0:
        return None
    points = []
    for k in comps[cand]:
        f = np.flatnonzero(labels == k)
        i = f[np.argmax(area2[f])]
        n = cross[i] / area2[i]
        points.append(tri[i].mean(0) - 1e-6 * np.sqrt(area2[i]) * n)
    points = np.asarray(points)
    step = max(1, 200_000 // len(tri))  # points per chunk: (step, T, 3) arrays of about 5 MB
    w = np.concatenate([winding_numbers(points[i : i + step], tri) for i in range(0, len(points), step)])
    bad = np.flatnonzero(np.abs(w - 1.0) > 0.25)
    return (int(comps[cand[bad[0]]]), bool(volume[cand[bad[0]]] < 0)) if len(bad) else None


def self_intersection(vertices: np.ndarray, faces: np.ndarray) -> tuple[int, int] | None:
    """A pair of faces (i, j), i < j, that share no vertex position and intersect (or touch); None if there is none.

    Faces sharing a vertex position (an edge or a corner of the mesh) are not tested: a crossing between two such
    faces elsewhere than at the shared features goes undetected. Broad phase: sweep and prune of the faces' boxes
    along the axis of largest extent; narrow phase: exact closest distance and edge-face crossings (about 0.1 s for
    a 20k-face icosphere, mostly box tests; a flat 150k-face slab, the sweep's bad case, takes about 2 s).
    ``(vertices, faces)`` must be finite and free of degenerate faces (:func:`check_mesh`).

    Args:
        vertices: (V, 3) float64 vertex positions.
        faces: (F, 3) integer vertex indices.
    """
    V = np.ascontiguousarray(vertices, dtype=np.float64)
    _, canon = np.unique(V, axis=0, return_inverse=True)  # one index per vertex position
    Fc = np.ascontiguousarray(canon.reshape(-1)[faces], dtype=np.int64)
    tri = np.ascontiguousarray(V[faces])  # (F, 3, 3)
    edge = np.linalg.norm(tri[:, [1, 2, 0]] - tri, axis=-1).max(1)  # (F,) longest edge
    pad = (_TOUCH_REL * edge)[:, None]
    lo, hi = tri.min(1) - pad, tri.max(1) + pad
    axis = int(np.argmax(hi.max(0) - lo.min(0)))
    order = np.argsort(lo[:, axis], kind="stable")
    i, j = _self_intersection_nb(tri, Fc, edge, lo, hi, order, axis, _TOUCH_REL)
    return None if i < 0 else (min(i, j), max(i, j))


@numba.njit(cache=True, error_model="numpy")
def _self_intersection_nb(tri, faces, edge, lo, hi, order, axis, rel):
    """Sweep over the faces' boxes sorted by their low end along ``axis``: the first vertex-disjoint pair that
    meets (see :func:`self_intersection`), or (-1, -1)."""
    F = tri.shape[0]
    a1, a2 = (axis + 1) % 3, (axis + 2) % 3
    out = np.empty(6)
    for s in range(F):
        i = order[s]
        for r in range(s + 1, F):
            j = order[r]
            if lo[j, axis] > hi[i, axis]:
                break
            if (
                lo[j, a1] > hi[i, a1]
                or lo[i, a1] > hi[j, a1]
                or lo[j, a2] > hi[i, a2]
                or lo[i, a2] > hi[j, a2]
            ):
                continue
            shared = False
            for u in range(3):
                for v in range(3):
                    if faces[i, u] == faces[j, v]:
                        shared = True
            if shared:
                continue
            A, B = tri[i], tri[j]
            tol = rel * max(edge[i], edge[j])
            if tri_tri_closest_nb(A, B, out) <= tol * tol:
                return i, j
            for k in range(3):
                k1 = k + 1 if k < 2 else 0
                if segment_hits_triangle_nb(A[k], A[k1], B, rel) or segment_hits_triangle_nb(
                    B[k], B[k1], A, rel
                ):
                    return i, j
    return -1, -1
