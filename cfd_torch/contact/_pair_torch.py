"""Batched tensor form of the pair solve and of its closed-form derivatives (any device).

The solve mirrors ``_pair_numba.solve_pairs`` (same start, damping rule and stopping test) as masked tensor code
over the still-active pairs, so it runs unchanged on CUDA. The derivative formulas here are also what the autograd
backward of ``pair_potential`` uses on every device.
"""

from __future__ import annotations

import torch

from .._geometry import triangle_closest_points

CONVERGED, INFEASIBLE, NOT_CONVERGED = 0, 1, 2
_STALL_TOL = 1e-8  # see _pair_numba
_EPS_RES = 16 * torch.finfo(torch.float64).eps
_GRAD_EPS = 16 * torch.finfo(torch.float64).eps
_MARGIN_RES = (
    64 * torch.finfo(torch.float64).eps
)  # a closest distance and the start gaps formed from it: their rounding, relative to the coordinates
_MAX_DAMP = 1e30
_ROT_COND = 1e-8  # see _pair_numba
_REFINE_STEPS = 8  # see _pair_numba
_REFINE_HALVINGS = 20
_REFINE_KAPPA = 1e6


def _sign(X: torch.Tensor) -> torch.Tensor:
    return torch.tensor([1.0, 1.0, 1.0, -1.0, -1.0, -1.0], dtype=X.dtype, device=X.device)


def gaps(X: torch.Tensor, P: torch.Tensor, half_delta: float) -> torch.Tensor:
    """(K, 6) vertex gaps s_k = sg_k (n . x_k + d) - delta/2 for planes P (K, 4)."""
    return _sign(X) * (torch.einsum("kvc,kc->kv", X, P[:, :3]) + P[:, 3:]) - half_delta


def energy(X: torch.Tensor, P: torch.Tensor, half_delta: float, lam: float) -> torch.Tensor:
    """(K,) E(p), +inf outside the feasible set."""
    r = torch.linalg.vector_norm(P[:, :3], dim=-1)
    s = gaps(X, P, half_delta)
    feasible = (r < 1.0) & (s > 0).all(-1)
    e = lam / (1.0 - r) + (1.0 / s).sum(-1)
    return torch.where(feasible, e, torch.full_like(e, float("inf")))


def plane_grad_hess(X: torch.Tensor, P: torch.Tensor, half_delta: float, lam: float):
    """dE/dp (K, 4), d2E/dp2 (K, 4, 4), rounding scale of each gradient component (K, 4), gaps (K, 6), the
    rounding resolution of E (K,), the plain scale of each gradient component (K, 4) (the sum of the magnitudes
    it is computed from, which the convergence test measures it against) and the Newton decrement that the gaps'
    own rounding gives (K,) (see ``_pair_numba._eval``).

    grad_p E = lam/(1-r)^2 [u; 0] - sum_k abar_k / s_k^2,  abar_k = sg_k [x_k; 1]
    hess_pp E = sum_k 2 abar_k abar_k^T / s_k^3 + lam [[Hn, 0], [0, 0]],
                Hn = 2/(1-r)^3 u u^T + (I - u u^T) / ((1-r)^2 r)
    """
    n = P[:, :3]
    r = torch.linalg.vector_norm(n, dim=-1, keepdim=True)  # (K, 1)
    u = n / r
    om = 1.0 - r
    s = gaps(X, P, half_delta)
    abar = _sign(X)[:, None] * torch.cat([X, torch.ones_like(X[..., :1])], -1)  # (K, 6, 4)
    w1 = 1.0 / (s * s)
    terms = abar * w1[..., None]  # (K, 6, 4)
    gn = lam / (om * om) * u
    g = torch.cat([gn, torch.zeros_like(r)], -1) - terms.sum(1)
    # rounding-noise scale per component: s carries an error of eps (|n.x| + |d|), amplified by 2 (...) / s
    mag = (X.abs() * n.abs()[:, None, :]).sum(-1) + P[:, 3:].abs() + half_delta  # (K, 6)
    amp = 1.0 + 2.0 * mag / s
    scale = torch.cat([gn.abs(), torch.zeros_like(r)], -1) + (terms.abs() * amp[..., None]).sum(1)
    plain = torch.cat([gn.abs(), torch.zeros_like(r)], -1) + terms.abs().sum(1)
    e_res = _EPS_RES * (
        lam / om.squeeze(-1) + (mag * w1).sum(-1)
    )  # rounding resolution of E (see _pair_numba)
    # the Newton decrement that the gaps' own rounding (eps mag_k each) gives: see _pair_numba._eval
    gap_noise2 = 2.0 * _GRAD_EPS**2 * (mag * mag * w1 / s).sum(-1)
    H = torch.einsum("kv,kvi,kvj->kij", 2.0 * w1 / s, abar, abar)
    eye = torch.eye(3, dtype=X.dtype, device=X.device)
    uu = u[:, :, None] * u[:, None, :]
    Hn = (2.0 / om**3)[..., None] * uu + (eye - uu) / (om * om * r)[..., None]
    H[:, :3, :3] += lam * Hn
    return g, H, scale, s, e_res, plain, gap_noise2


def contact_frame(X: torch.Tensor, P: torch.Tensor, half_delta: float):
    """(X - o (K, 6, 3), P in the frame at o (K, 4), o (K, 3)): o is the vertices' centroid weighted by
    (min_j |s_j| / |s_k|)^3 at the planes P (K, 4) (the weights of the gaps in E_pp, 2 / s_k^3, normalised), a point
    in the contact region.

    The solve and the derivatives are formed there: a gap n.x + d of a pair in contact at a distance R from the
    origin is a difference of terms of size R (absolute rounding eps R), and the plane's tilt about the contact,
    set by the far vertices and the regulariser, is lost in E_pp's entries R^2 / s^3 at the rounding of the
    closest ones; about o, the close vertices' lever arms (and their gaps' rounding) are the size of the contact.
    o itself need not be exact: X - o rounds to eps |X - o|, a backward error of one ulp of the geometry."""
    sg = _sign(X)
    s = sg * (torch.einsum("kvc,kc->kv", X, P[:, :3]) + P[:, 3:]) - half_delta
    a = s.abs()
    m = a.amin(-1, keepdim=True)
    w = torch.where(a <= m, torch.ones_like(a), (m / a) ** 3)
    o = (w[..., None] * X).sum(1) / w.sum(-1, keepdim=True)
    o = torch.where(torch.isfinite(o), o, torch.zeros_like(o))
    d = P[:, 3] + (P[:, :3] * o).sum(-1)
    return X - o[:, None, :], torch.cat([P[:, :3], d[:, None]], -1), o


def clear_of_margin(dist: torch.Tensor, delta: float, X: torch.Tensor) -> torch.Tensor:
    """(K,) bool: the pairs (K, 6, 3) whose closest distance ``dist`` exceeds the margin ``delta`` by more than its
    rounding (``_MARGIN_RES`` of the coordinates' magnitude; the numba kernel's ``_clear_of_margin``). Closer pairs
    are infeasible: at a gap within rounding of the margin the barrier has no resolvable minimum, and the two
    backends' starts would disagree about it."""
    scale = X.abs().flatten(1).amax(1).clamp_min(delta)
    return dist - delta > _MARGIN_RES * scale


def start_planes(X: torch.Tensor, delta: float) -> tuple[torch.Tensor, torch.Tensor]:
    """Strictly feasible start from the exact closest points (SPEC section 2); returns planes (K, 4) and dist (K,).

    With the mid-gap plane along n0 = (qa - qb)/|qa - qb| scaled by alpha = (delta/2 + 1)/(dist/2 + 1), every gap is
    >= (dist - delta)/2 / (dist/2 + 1) > 0 and |n| = alpha < 1 whenever dist > delta. Where rounding makes that
    plane infeasible (large triangles a few margins apart: the direction of qa - qb tilts it by more than the gap),
    the same construction along the best separating axis instead (:func:`sat_planes`).
    """
    dist, qa, qb = triangle_closest_points(X[:, :3], X[:, 3:])
    safe = torch.where(dist > 0, dist, torch.ones_like(dist))
    alpha = (0.5 * delta + 1.0) / (0.5 * safe + 1.0) / safe
    n = alpha[:, None] * (qa - qb)
    d = -(n * 0.5 * (qa + qb)).sum(-1, keepdim=True)
    P = torch.cat([n, d], -1)
    s = gaps(X, P, 0.5 * delta)
    bad = clear_of_margin(dist, delta, X) & ~((s > 0).all(-1) & (n.norm(dim=-1) < 1))
    if bool(bad.any()):
        P[bad] = sat_planes(X[bad], delta)
    return P, dist


_SPLIT = 134217729.0  # Dekker's splitter for float64: x = hi + lo exactly, each half with at most 26 bits


def _two_prod(a: torch.Tensor, b: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """a b = p + e exactly (Dekker's product; float64)."""
    t = _SPLIT * a
    ah = t - (t - a)
    al = a - ah
    t = _SPLIT * b
    bh = t - (t - b)
    bl = b - bh
    p = a * b
    return p, ((ah * bh - p) + ah * bl + al * bh) + al * bl


def _cross2(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """a x b (..., 3), each component to about an ulp of itself, however nearly parallel a and b are
    (``_pair_numba._cross2``)."""
    i, j = [1, 2, 0], [2, 0, 1]
    p, ep = _two_prod(a[..., i], b[..., j])
    q, eq = _two_prod(a[..., j], b[..., i])
    return (p - q) + (ep - eq)


def sat_planes(X: torch.Tensor, delta: float) -> torch.Tensor:
    """(K, 4) the mid-gap plane along the separating axis with the largest separation (of 26: the triangles'
    normals, the 9 cross products of their edges, the 6 in-plane edge normals and, for each edge of a and vertex of
    b, the perpendicular from the edge's line to the vertex; cross products to an ulp of their components), scaled
    like the closest-point start (``_pair_numba._sat_start``)."""
    ea = X[:, [1, 2, 0]] - X[:, :3]  # (K, 3, 3) edges of a
    eb = X[:, [4, 5, 3]] - X[:, 3:]
    na = _cross2(ea[:, 0], -ea[:, 2])  # normal of a
    nb = _cross2(eb[:, 0], -eb[:, 2])
    E = ea[:, :, None, :].expand(-1, 3, 3, 3)  # (K, i, j, 3): edge i of a
    w = X[:, None, 3:, :] - X[:, :3, None, :]  # (K, i, j, 3): vertex j of b - start of edge i of a
    axes = torch.cat(
        [
            na[:, None],
            nb[:, None],
            _cross2(E, eb[:, None].expand(-1, 3, 3, 3)).flatten(1, 2),
            _cross2(na[:, None].expand(-1, 3, 3), ea),  # in-plane edge normals: coplanar triangles
            _cross2(nb[:, None].expand(-1, 3, 3), eb),
            _cross2(_cross2(w, E), E).flatten(1, 2),  # perpendiculars from a's edge lines: parallel edges
        ],
        1,
    )  # (K, 26, 3)
    norm = axes.norm(dim=-1, keepdim=True)
    u = axes / torch.where(norm > 0, norm, torch.ones_like(norm))
    t = torch.einsum("kcj,kvj->kcv", u, X)  # (K, 26, 6) projections
    amin, amax = t[..., :3].amin(-1), t[..., :3].amax(-1)
    bmin, bmax = t[..., 3:].amin(-1), t[..., 3:].amax(-1)
    up, down = amin - bmax, bmin - amax  # a above, a below
    sep = torch.where(norm[..., 0] > 0, torch.maximum(up, down), torch.full_like(up, -torch.inf))
    best = sep.argmax(1)
    k = torch.arange(X.shape[0], device=X.device)
    sgn = torch.where(up[k, best] >= down[k, best], 1.0, -1.0).to(X.dtype)
    mid = torch.where(sgn > 0, 0.5 * (amin + bmax)[k, best], 0.5 * (bmin + amax)[k, best])
    alpha = sgn * (0.5 * delta + 1.0) / (0.5 * sep[k, best] + 1.0)
    return torch.cat([alpha[:, None] * u[k, best], (-alpha * mid)[:, None]], -1)


def solve_pairs_torch(X: torch.Tensor, delta: float, lam: float, tol: float, max_iter: int):
    """Masked batched Levenberg-Marquardt over all pairs.

    Args:
        X: (K, 6, 3) float64 vertices a0, a1, a2, b0, b1, b2.

    Returns:
        P (K, 4) planes in the frame at o, E (K,) energies (+inf where infeasible), status (K,) int8, resid (K,)
        relative gradients, o (K, 3) the contact frame's origins (:func:`contact_frame`) and X - o (K, 6, 3).
    """
    half_delta = 0.5 * delta
    K = X.shape[0]
    P, dist = start_planes(X, delta)
    X, P, o = contact_frame(X, P, half_delta)
    E = energy(X, P, half_delta, lam)
    E = torch.where(clear_of_margin(dist, delta, X), E, torch.full_like(E, float("inf")))
    status = torch.full((K,), NOT_CONVERGED, dtype=torch.int8, device=X.device)
    status[torch.isinf(E)] = INFEASIBLE
    resid = torch.zeros(K, dtype=X.dtype, device=X.device)
    act = torch.nonzero(status == NOT_CONVERGED).squeeze(-1)
    damp = torch.zeros(act.shape[0], dtype=X.dtype, device=X.device)
    n_accepted = torch.zeros(act.shape[0], dtype=torch.int64, device=X.device)
    eye4 = torch.eye(4, dtype=X.dtype, device=X.device)
    for _ in range(max_iter * 8):  # accepted steps are capped by max_iter; rejected trials by the damping cap
        if act.numel() == 0:
            break
        Xa, Pa, Ea = X[act], P[act], E[act]
        g, H, scale, _, e_res, plain, gap_noise2 = plane_grad_hess(Xa, Pa, half_delta, lam)
        rel = torch.where(scale > 0, g.abs() / scale, torch.zeros_like(g)).amax(-1)  # 0/0: an exact zero
        rel_plain = torch.where(plain > 0, g.abs() / plain, torch.zeros_like(g)).amax(-1)
        resid[act] = rel
        Hd = H + torch.diag_embed(torch.diagonal(H, dim1=-2, dim2=-1) * damp[:, None])
        L, info = torch.linalg.cholesky_ex(Hd)
        spd = info == 0
        L = torch.where(spd[:, None, None], L, eye4)
        step = torch.cholesky_solve(-g[..., None], L).squeeze(-1)
        dec2 = -(g * step).sum(-1)
        y = torch.linalg.solve_triangular(L, (_GRAD_EPS * plain)[..., None], upper=False).squeeze(-1)
        noise2 = (y * y).sum(-1) + gap_noise2
        # the stopping rules of _pair_numba.solve_pairs
        done = (rel_plain <= tol) | (spd & (damp == 0) & ((dec2 <= tol * tol * Ea) | (dec2 <= noise2)))
        stalled = damp > _MAX_DAMP
        finished = done | stalled | (n_accepted >= max_iter)
        # a stalled pair, or one at the iteration cap, whose relative gradient is below _STALL_TOL: in the Newton
        # endgame steps that change E by less than its rounding are accepted, and a badly conditioned pair can keep
        # taking them without its gradient reaching tol; it is as converged as the stalled ones
        status[act[done | ((stalled | (n_accepted >= max_iter)) & (rel <= _STALL_TOL))]] = CONVERGED
        keep = ~finished
        act, damp, n_accepted = act[keep], damp[keep], n_accepted[keep]
        Xa, Pa, Ea, step, dec2, spd, e_res = (
            Xa[keep],
            Pa[keep],
            Ea[keep],
            step[keep],
            dec2[keep],
            spd[keep],
            e_res[keep],
        )
        trial = Pa + step
        Et = energy(Xa, trial, half_delta, lam)
        accept = spd & ((Et <= Ea) | ((dec2 <= e_res) & (Et <= Ea + e_res)))
        P[act] = torch.where(accept[:, None], trial, Pa)
        E[act] = torch.where(accept, Et, Ea)
        n_accepted = n_accepted + accept.to(torch.int64)
        damp = torch.where(
            accept,
            torch.where(damp <= 1e-3, torch.zeros_like(damp), damp * 0.1),
            torch.where(damp == 0, torch.full_like(damp, 1e-4), damp * 10.0),
        )
    # the Newton step from each converged plane is taken too, where E stays within its resolution (as in
    # _pair_numba.solve_pairs: it makes the plane's error, which the derivatives depend on, quadratically small)
    conv = torch.nonzero(status == CONVERGED).squeeze(-1)
    if conv.numel():
        Xc, Pc, Ec = X[conv], P[conv], E[conv]
        g, H, _, _, e_res, _, _ = plane_grad_hess(Xc, Pc, half_delta, lam)
        L, info = torch.linalg.cholesky_ex(H)
        spd = info == 0
        step = torch.cholesky_solve(-g[..., None], torch.where(spd[:, None, None], L, eye4)).squeeze(-1)
        trial = Pc + step
        Et = energy(Xc, trial, half_delta, lam)
        take = spd & (Et <= Ec + e_res)
        Pc = torch.where(take[:, None], trial, Pc)
        Ec = torch.where(take, Et, Ec)
        # the ill-conditioned pairs (``_pair_numba._conditioning``, max_k |n| |x_k| / s_k, then E_pp's pivots)
        s = gaps(Xc, Pc, half_delta)
        cond = (
            torch.linalg.vector_norm(Pc[:, None, :3], dim=-1) * torch.linalg.vector_norm(Xc, dim=-1) / s
        ).amax(-1)
        ill = torch.nonzero(cond > _REFINE_KAPPA).squeeze(-1)
        if ill.numel():
            H = plane_grad_hess(Xc[ill], Pc[ill], half_delta, lam)[1]
            ill = ill[_ill_conditioned(H)]
        if ill.numel():
            Pc[ill], Ec[ill] = _refine(Xc[ill], Pc[ill], Ec[ill], half_delta, lam)
        P[conv], E[conv] = Pc, Ec
    return P, E, status, resid, o, X


def pair_vertex_grad(X: torch.Tensor, P: torch.Tensor, half_delta: float) -> torch.Tensor:
    """(K, 6, 3) dE/dx_k = -sg_k n / s_k^2 at planes P (envelope theorem), without the second-order pieces."""
    s = gaps(X, P, half_delta)
    return -(_sign(X) / (s * s))[..., None] * P[:, None, :3]


def pair_derivative_parts(X: torch.Tensor, P: torch.Tensor, half_delta: float, lam: float):
    """Closed-form pieces at the optimal plane: gaps s (K, 6), E_x (K, 6, 3), E_xp (K, 18, 4), E_pp (K, 4, 4).

    dE/dx_k    = -sg_k n / s_k^2
    d2E/dx_k2  = 2 n n^T / s_k^3            (block diagonal)
    d2E/dx_k dp = -sg_k [I3 | 0] / s_k^2 + 2 n [x_k^T | 1] / s_k^3
    """
    _, Epp, _, s, _, _, _ = plane_grad_hess(X, P, half_delta, lam)
    n = P[:, :3]
    sg = _sign(X)
    w1 = 1.0 / (s * s)
    w2 = 2.0 * w1 / s
    Ex = -(sg * w1)[..., None] * n[:, None, :]  # (K, 6, 3)
    xh = torch.cat([X, torch.ones_like(X[..., :1])], -1)  # (K, 6, 4)
    eye = torch.eye(3, 4, dtype=X.dtype, device=X.device)
    Exp = -(sg * w1)[..., None, None] * eye + w2[..., None, None] * n[:, None, :, None] * xh[:, :, None, :]
    return s, Ex, Exp.reshape(-1, 18, 4), Epp  # Exp: (K, 18, 4)


def _cholesky(A: torch.Tensor) -> torch.Tensor:
    """Cholesky factors of the (K, 4, 4) E_pp; where rounding leaves one not positive definite (pairs within
    about 1e-14 of the margin: condition numbers beyond 1e30), with a diagonal shift growing from 16 eps of its
    largest diagonal entry until it is (the numba kernel's factorisation gets the same matrices)."""
    L, info = torch.linalg.cholesky_ex(A)
    shift = 16 * torch.finfo(A.dtype).eps
    while bool((info != 0).any()) and shift < 1.0:
        bad = info != 0
        scale = torch.diagonal(A[bad], dim1=-2, dim2=-1).amax(-1)
        eye = torch.eye(4, dtype=A.dtype, device=A.device)
        Lb, ib = torch.linalg.cholesky_ex(A[bad] + (shift * scale)[:, None, None] * eye)
        L[bad], info[bad] = Lb, ib
        shift *= 16.0
    return L


def _ill_conditioned(Epp: torch.Tensor) -> torch.Tensor:
    """(K,) whether E_pp (K, 4, 4) has a Cholesky pivot below _ROT_COND of its largest diagonal entry (or none)."""
    L, info = torch.linalg.cholesky_ex(Epp)
    piv = torch.diagonal(L, dim1=-2, dim2=-1).amin(-1) ** 2
    dmax = torch.diagonal(Epp, dim1=-2, dim2=-1).amax(-1)
    return (info != 0) | ~(piv >= _ROT_COND * dmax)


def _rotated(X: torch.Tensor, P: torch.Tensor, s: torch.Tensor, Epp: torch.Tensor, lam: float):
    """E_pp's eigenbasis Q (K, 4, 4), B_k = Q^T [x_k; 1] (K, 6, 4), Q^T E_pp Q formed from B (K, 4, 4) and Q^T
    grad_p E formed from B (K, 4) (``_pair_numba._rotated_epp`` and ``_refine``)."""
    _, Q = torch.linalg.eigh(Epp)
    xh = torch.cat([X, torch.ones_like(X[..., :1])], -1)  # (K, 6, 4)
    Bk = torch.einsum("kvi,kia->kva", xh, Q)
    w1 = 1.0 / (s * s)
    w2 = 2.0 * w1 / s
    n = P[:, :3]
    r = torch.linalg.vector_norm(n, dim=-1)
    om = 1.0 - r
    gl = lam / (om * om)
    c2 = gl / r
    c12 = 2.0 * gl / om - c2
    Q3 = Q[:, :3, :]
    uq = torch.einsum("ki,kia->ka", n, Q3) / r[:, None]
    Eq = torch.einsum("kv,kva,kvb->kab", w2, Bk, Bk)
    Eq = (
        Eq
        + c12[:, None, None] * uq[:, :, None] * uq[:, None, :]
        + c2[:, None, None] * (Q3.transpose(1, 2) @ Q3)
    )
    gq = gl[:, None] * uq - torch.einsum("kv,kva->ka", _sign(X) * w1, Bk)
    return Q, Bk, Eq, gq


def _refine(X: torch.Tensor, P: torch.Tensor, E: torch.Tensor, half_delta: float, lam: float):
    """Newton steps in E_pp's eigenbasis from converged planes P of ill-conditioned pairs (``_pair_numba._refine``:
    there the gradient's weak components keep their digits); returns the refined (P, E)."""
    eps = torch.finfo(X.dtype).eps
    for _ in range(_REFINE_STEPS):
        _, Epp, _, s, e_res, _, _ = plane_grad_hess(X, P, half_delta, lam)
        Q, _, Eq, gq = _rotated(X, P, s, Epp, lam)
        dq = torch.cholesky_solve(-gq[..., None], _cholesky(Eq)).squeeze(-1)
        dp = (Q @ dq[..., None]).squeeze(-1)
        r = torch.linalg.vector_norm(P[:, :3], dim=-1)
        moving = dp.abs().amax(-1) > 4 * eps * r
        take = torch.zeros_like(moving)
        t = torch.ones_like(E)
        for _ in range(_REFINE_HALVINGS):  # backtrack to a feasible plane whose E stays within its rounding
            Et = energy(X, P + t[:, None] * dp, half_delta, lam)
            ok = moving & ~take & (Et <= E + e_res)
            P = torch.where(ok[:, None], P + t[:, None] * dp, P)
            E = torch.where(ok, Et, E)
            take = take | ok
            if bool((take | ~moving).all()):
                break
            t = torch.where(take, t, 0.5 * t)
        if not bool(take.any()):
            break
    return P, E


def _schur_parts(X: torch.Tensor, P: torch.Tensor, half_delta: float, lam: float):
    """Gaps s (K, 6), E_px (K, 18, 4) and the Cholesky factor of E_pp (K, 4, 4). Where E_pp is ill-conditioned
    (a pivot below _ROT_COND of its largest diagonal entry) both are expressed in E_pp's eigenbasis Q instead:
    E_px Q and Q^T E_pp Q, formed from B_k = Q^T [x_k; 1] (``_pair_numba._rotated_epp``: in (n, d) coordinates
    E_pp's weak directions round away). The Schur complement E_xp E_pp^-1 E_px does not depend on the basis."""
    s, _, Exp, Epp = pair_derivative_parts(X, P, half_delta, lam)
    bad = _ill_conditioned(Epp)
    if bool(bad.any()):
        Xb, Pb, sb = X[bad], P[bad], s[bad]
        Q, Bk, Eq, _ = _rotated(Xb, Pb, sb, Epp[bad], lam)
        w1 = 1.0 / (sb * sb)
        w2 = 2.0 * w1 / sb
        n = Pb[:, :3]
        Q3 = Q[:, :3, :]
        sg = _sign(Xb)
        # rows (k, j): Q^T (2 n_j [x_k; 1] / s^3 - sg e_j / s^2)
        Eb = (
            w2[..., None, None] * n[:, None, :, None] * Bk[:, :, None, :]
            - (sg * w1)[..., None, None] * Q3[:, None]
        )
        Exp = Exp.clone()
        Exp[bad] = Eb.reshape(-1, 18, 4)
        Epp = Epp.clone()
        Epp[bad] = Eq
    return s, Exp, _cholesky(Epp)


def pair_hessian_torch(
    X: torch.Tensor, P: torch.Tensor, mu: float, half_delta: float, lam: float
) -> torch.Tensor:
    """(K, 18, 18) hess_x P = mu (E_xx - E_xp E_pp^-1 E_px) (implicit function theorem)."""
    s, Exp, L = _schur_parts(X, P, half_delta, lam)
    n = P[:, :3]
    W = torch.linalg.solve_triangular(L, Exp.transpose(1, 2), upper=False)  # (K, 4, 18) = L^-1 E_px
    Hs = -W.transpose(1, 2) @ W
    blocks = (2.0 / s**3)[..., None, None] * n[:, None, :, None] * n[:, None, None, :]  # (K, 6, 3, 3)
    Hs.view(-1, 6, 3, 6, 3).diagonal(dim1=1, dim2=3).add_(blocks.permute(0, 2, 3, 1))
    return mu * Hs


def pair_hessian_vjp(
    X: torch.Tensor, P: torch.Tensor, v: torch.Tensor, mu: float, half_delta: float, lam: float
):
    """(K, 18) v^T hess_x P without forming the 18 x 18 Hessian: mu (v^T E_xx - (v^T E_xp) E_pp^-1 E_px)."""
    s, Exp, L = _schur_parts(X, P, half_delta, lam)
    n = P[:, :3]
    v6 = v.reshape(-1, 6, 3)
    direct = (2.0 / s**3 * (v6 * n[:, None, :]).sum(-1))[..., None] * n[:, None, :]  # (K, 6, 3)
    # (matmuls, not einsums: autograd.functional's vectorize=True has batching rules for these only)
    y = (v[:, None, :] @ Exp)[:, 0]  # (K, 4)
    z = torch.cholesky_solve(y[..., None], L)
    return mu * (direct.reshape(-1, 18) - (Exp @ z)[..., 0])
