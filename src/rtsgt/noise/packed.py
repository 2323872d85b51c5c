"""Packed symmetric 3x3 matrices of many points, (6, N) rows xx, yy, zz, xy, xz, yz.

The first-order engine (:mod:`rtsgt.noise.linear`) and the noise sources' first-order terms
(:mod:`rtsgt.noise.sources`) accumulate covariances in this form, structure of arrays.
"""

from __future__ import annotations

import numpy as np

#: The packed components' (row, column) in the 3x3 matrix.
SYM = ((0, 0), (1, 1), (2, 2), (0, 1), (0, 2), (1, 2))
_SYM_INDEX = np.array([0, 3, 4, 3, 1, 5, 4, 5, 2])  # (i, j) row-major -> packed component


def small_matmul(A: np.ndarray, X: np.ndarray) -> np.ndarray:
    """``A @ X`` for a small ``A`` (k, m) and a wide ``X`` (m, N), single-threaded (a BLAS call
    would start its thread pool for a product this skinny)."""
    return np.einsum("ij,jn->in", A, X)


def packed_outer(terms, n: int) -> np.ndarray:
    """Packed ``sum_k w_k v_k v_k^T``, (6, N); ``terms``: iterable of ``(v, w)``, ``v`` (3, N)
    contiguous rows, ``w`` a scalar or (N,)."""
    acc = np.zeros((6, n))
    for v, w in terms:
        vw = v * w
        for k, (i, j) in enumerate(SYM):
            acc[k] += vw[i] * v[j]
    return acc


def unpack(acc: np.ndarray) -> np.ndarray:
    """(6, N) packed symmetric matrices -> (N, 3, 3)."""
    return acc.T[:, _SYM_INDEX].reshape(-1, 3, 3)  # fancy indexing: a fresh C-ordered copy
