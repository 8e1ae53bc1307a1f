"""CPU kernel of :func:`cfd_torch.contact.model.sum_pairs` (no autograd): per-pair derivatives added into per-pose-set
ones in one loop, without the tensor version's grouping and block reshapes."""

from __future__ import annotations

import numba
import numpy as np


@numba.njit(cache=True, error_model="numpy")
def scatter_pairs(S, N, pairs, g, h, want_g, want_h):
    """G (S, N, 6) += each row's g (P, 12) at bodies i, j of set s; H (S, 6 N, 6 N) += its h (P, 12, 12) blocks
    (i|j, i|j), rows ``pairs`` (P, 3) = (s, i, j), in row order."""
    P = pairs.shape[0]
    G = np.zeros((S if want_g else 0, N, 6))
    H = np.zeros((S if want_h else 0, 6 * N, 6 * N))
    for r in range(P):
        s = pairs[r, 0]
        for side in range(2):
            b = pairs[r, 1 + side]
            if want_g:
                for k in range(6):
                    G[s, b, k] += g[r, 6 * side + k]
            if want_h:
                for side2 in range(2):
                    b2 = pairs[r, 1 + side2]
                    for k in range(6):
                        for l in range(6):
                            H[s, 6 * b + k, 6 * b2 + l] += h[r, 6 * side + k, 6 * side2 + l]
    return G, H
