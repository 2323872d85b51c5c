"""Normal equations of the joint engine: block-tridiagonal knots plus an arrow of globals.

Block cyclic reduction (a loop over its log2(K) levels, batched over the blocks of a level)
and the Schur complement onto the global parameters: docs/joint.md#the-solver.
"""

from __future__ import annotations

import warnings
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np
from scipy.linalg import LinAlgWarning
from scipy.linalg import inv as _lapack_inv

from rtsgt.parallel import available_cores

#: Threads that share the reduction's batched products (:mod:`rtsgt.parallel`).
_CORES = available_cores()
#: Fewest blocks of a product worth a thread of their own (a thread's start costs more).
_MIN_PER_THREAD = 512


@dataclass(frozen=True)
class ArrowSystem:
    """``[[A, B], [B^T, C]] [x; g] = [a; c]``: ``A`` block tridiagonal, diagonal blocks ``D``
    (K, d, d), upper blocks ``U`` (K-1, d, d) (``A_k,k+1``); ``B`` (K, d, G); ``C`` (G, G);
    ``a`` (K, d); ``c`` (G,)."""

    D: np.ndarray
    U: np.ndarray
    B: np.ndarray
    C: np.ndarray
    a: np.ndarray
    c: np.ndarray

    def dense(self) -> tuple[np.ndarray, np.ndarray]:
        """The whole matrix (K d + G, K d + G) and right-hand side (tests, small systems)."""
        K, d, _ = self.D.shape
        G = self.C.shape[0]
        n = K * d
        M = np.zeros((n + G, n + G))
        for k in range(K):
            M[k * d:(k + 1) * d, k * d:(k + 1) * d] = self.D[k]
        for k in range(K - 1):
            M[k * d:(k + 1) * d, (k + 1) * d:(k + 2) * d] = self.U[k]
            M[(k + 1) * d:(k + 2) * d, k * d:(k + 1) * d] = self.U[k].T
        M[:n, n:] = self.B.reshape(n, G)
        M[n:, :n] = self.B.reshape(n, G).T
        M[n:, n:] = self.C
        return M, np.concatenate([self.a.ravel(), self.c])


def knot_rows(index: np.ndarray, n: int, values: np.ndarray) -> np.ndarray:
    """``values`` (M, r, ...) of ``M`` items, item ``i`` at knot ``index[i]`` (below ``n``),
    as each knot's rows (n, R r, ...): its items' in their order, ``R`` the most items at one
    knot, zero past a knot's own. A sum over each knot's items of ``A_i^T B_i`` is then one
    batched product of their rows, ``rows(A)^T rows(B)`` (n, ., .), without an (M, ., .)
    product to sum (the measurements' normal equations; a knot has one to three)."""
    index = np.asarray(index, dtype=int)
    counts = np.bincount(index, minlength=n)
    order = np.argsort(index, kind="stable")
    pos = np.empty(index.size, dtype=int)
    pos[order] = np.arange(index.size) - (np.cumsum(counts) - counts)[index[order]]
    R = int(counts.max(initial=1))
    out = np.zeros((n, R) + values.shape[1:])
    out[index, pos] = values
    return out.reshape((n, R * values.shape[1]) + values.shape[2:])


def add_transitions(D: np.ndarray, U: np.ndarray, a: np.ndarray, cols: slice, e: np.ndarray,
                    E: np.ndarray, F: np.ndarray, W: np.ndarray) -> float:
    """Adds terms between consecutive knots to their normal equations ``D`` (K, d, d), ``U``
    (K-1, d, d), ``a`` (K, d) (in place): each interval's error ``e`` (K-1, n) with
    information ``W`` (K-1, n, n) and Jacobians ``E``, ``F`` (K-1, n, n) wrt the knots' states
    ``cols`` (n of d) at its start and end (a motion prior, a chain's transition); returns
    their cost ``sum e^T W e``."""
    EtW, FtW = np.swapaxes(E, 1, 2) @ W, np.swapaxes(F, 1, 2) @ W
    D[:-1, cols, cols] += EtW @ E
    D[1:, cols, cols] += FtW @ F
    U[:, cols, cols] += EtW @ F
    a[:-1, cols] -= np.einsum("kij,kj->ki", EtW, e)
    a[1:, cols] -= np.einsum("kij,kj->ki", FtW, e)
    return float(np.einsum("ki,kij,kj->", e, W, e))


#: Knots (or measurements) per block of the products whose temporaries have a knot's or the
#: globals' width (the globals' share of the knots' covariance, the measurements' share of
#: it and their ``H Sigma H^T``): bounds them on an hour's run.
CHUNK = 2048


def chunks(n: int, size: int | None = None):
    """Slices covering ``range(n)`` in order, each of at most ``size`` (:data:`CHUNK`)."""
    size = CHUNK if size is None else size
    return (slice(lo, min(n, lo + size)) for lo in range(0, n, size))


@dataclass(frozen=True)
class ArrowSolution:
    """Solution ``x`` (K, d), ``g`` (G,) of an :class:`ArrowSystem` and, where asked, the
    covariances (the inverse of its matrix): the knots' blocks ``cov`` (K, d, d), those of
    consecutive knots ``cov_next`` (K-1, d, d) (``Sigma_k,k+1``) and the globals' ``cov_g``
    (G, G); their split (docs/joint.md#the-shared-error): ``cov_var`` (K, d, d) and
    ``cov_var_next`` (K-1, d, d) the blocks of ``A^-1`` (the knots' error given the
    globals), ``factor`` (K, d, G) ``L_k = -Y_B,k chol(S^-1)`` (the knots' error per unit
    whitened global error, ``cov = cov_var + L L^T``) and ``chol_g`` (G, G) the lower
    Cholesky factor of ``cov_g`` (``Cov(x_k, g) = L_k chol_g^T``; with more whitened errors
    than globals, :func:`add_shared_columns`, ``factor`` (K, d, G') and ``chol_g`` (G, G'));
    ``own`` where this is a mixture of hypotheses (:func:`mix_solutions`), the estimate's
    own solution: the posterior of its least squares, whose fitted residuals the deletion
    residuals are (:func:`rtsgt.joint.blockcv.raw_block_cv`)."""

    x: np.ndarray
    g: np.ndarray
    cov: np.ndarray | None
    cov_next: np.ndarray | None
    cov_g: np.ndarray | None
    cov_var: np.ndarray | None = None
    cov_var_next: np.ndarray | None = None
    factor: np.ndarray | None = None
    chol_g: np.ndarray | None = None
    own: ArrowSolution | None = None


def _add_outer(cov: np.ndarray, cov_next: np.ndarray, lx: np.ndarray) -> None:
    """Adds the shared columns ``lx`` (K, d, n) to the knots' covariances ``cov`` (K, d, d)
    and consecutive ones' ``cov_next`` (K-1, d, d), in place, a few thousand knots at a
    time: ``lx_k lx_k^T`` and ``lx_k lx_k+1^T``."""
    for sl in chunks(cov.shape[0]):
        cov[sl] += lx[sl] @ np.swapaxes(lx[sl], 1, 2)
    for sl in chunks(cov_next.shape[0]):
        cov_next[sl] += lx[sl] @ np.swapaxes(lx[sl.start + 1:sl.stop + 1], 1, 2)


def add_shared_columns(sol: ArrowSolution, dx: np.ndarray, dg: np.ndarray) -> ArrowSolution:
    """``sol`` with ``n`` more whitened shared errors: the knots' error ``dx`` (n, K, d) and
    the globals' ``dg`` (n, G) per unit of each (an unknown that moves every state at once:
    docs/joint.md#which-prism-moved), as columns of ``factor`` (K, d, G' + n) and ``chol_g``
    (G, G' + n) (no longer square), added to ``cov``, ``cov_next`` and ``cov_g``; the
    solution ``x``, ``g`` and the knots' part given the globals (``cov_var``,
    ``cov_var_next``) are kept."""
    lx = np.moveaxis(dx, 0, -1)  # (K, d, n)
    cov, cov_next = sol.cov.copy(), sol.cov_next.copy()
    _add_outer(cov, cov_next, lx)
    return ArrowSolution(sol.x, sol.g, cov, cov_next, sol.cov_g + dg.T @ dg, sol.cov_var,
                         sol.cov_var_next, np.concatenate([sol.factor, lx], axis=2),
                         np.concatenate([sol.chol_g, dg.T], axis=1))


def mix_solutions(sols: list[ArrowSolution], w: np.ndarray, dx: np.ndarray, dg: np.ndarray
                  ) -> ArrowSolution:
    """The mixture of the solutions ``sols`` (each with covariances) with weights ``w`` (n,)
    about the first's estimate (docs/joint.md#which-prism-moved): ``dx`` (n-1, K, d) and
    ``dg`` (n-1, G) each other solution's difference from the first's, so that
    ``Sigma = sum_i w_i (Sigma_i + delta_i delta_i^T)`` (``delta_1 = 0``). Its split: the
    knots' part given the globals ``sum_i w_i cov_var_i`` (so too ``cov_var_next``), and
    the shared columns of every solution's ``factor``, ``chol_g`` and the differences, each
    times ``sqrt(w_i)`` (as :func:`add_shared_columns` adds them; here each array is made
    once, the hour's mixture being its run's peak of memory). The first's ``x``, ``g``; each
    covariance is taken in its own state's tangent space, the differences' order
    neglected; ``own`` the first (:class:`ArrowSolution`)."""
    r = np.sqrt(w)
    lx = np.moveaxis(r[1:, None, None] * dx, 0, -1)  # (K, d, n-1): the differences' columns
    K = sols[0].cov.shape[0]

    def mean(name):  # one new array, summed a few thousand knots at a time
        out = w[0] * getattr(sols[0], name)
        for wi, s in zip(w[1:], sols[1:], strict=True):
            for sl in chunks(out.shape[0]):
                out[sl] += wi * getattr(s, name)[sl]
        return out

    cov, cov_next = mean("cov"), mean("cov_next")
    _add_outer(cov, cov_next, lx)
    widths = np.cumsum([0] + [s.factor.shape[2] for s in sols] + [lx.shape[2]])
    factor = np.empty((K, cov.shape[1], widths[-1]))  # every solution's columns, then lx's
    for sl in chunks(K):
        for ri, s, lo, hi in zip(r, sols, widths[:-2], widths[1:-1], strict=True):
            factor[sl, :, lo:hi] = ri * s.factor[sl]
        factor[sl, :, widths[-2]:] = lx[sl]
    dgw = r[1:, None] * dg
    chol_g = np.concatenate([ri * s.chol_g for ri, s in zip(r, sols, strict=True)] + [dgw.T],
                            axis=1)
    cov_g = sum(wi * s.cov_g for wi, s in zip(w, sols, strict=True)) + dgw.T @ dgw
    return ArrowSolution(sols[0].x, sols[0].g, cov, cov_next, cov_g, mean("cov_var"),
                         mean("cov_var_next"), factor, chol_g, own=sols[0])


def _bmm(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``a @ b`` of two stacks (n, p, q), (n, q, r), the stack split between up to
    :data:`_CORES` threads where it is long (numpy releases the interpreter lock in its
    products). Each block's product is BLAS's alone, so the numbers do not depend on the
    threads."""
    n = a.shape[0]
    parts = min(_CORES, n // _MIN_PER_THREAD)
    if parts < 2 or a.ndim != 3 or b.ndim != 3 or b.shape[0] != n:
        return a @ b
    out = np.empty((n, a.shape[1], b.shape[2]), dtype=np.result_type(a, b))
    edges = np.linspace(0, n, parts + 1).astype(int)

    def part(i: int) -> None:
        sl = slice(edges[i], edges[i + 1])
        np.matmul(a[sl], b[sl], out=out[sl])

    with ThreadPoolExecutor(max_workers=parts) as ex:
        list(ex.map(part, range(parts)))
    return out


def _spd_inv(a: np.ndarray) -> np.ndarray:
    """Inverses (..., d, d) of SPD blocks through their Cholesky factors (LAPACK's
    ``potrf``, ``potri``; raises :class:`numpy.linalg.LinAlgError` where one is not
    positive definite; an ill-conditioned block is the caller's to judge, not warned of)."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", LinAlgWarning)
        return _lapack_inv(a, assume_a="pos", check_finite=False)


def _sym(a: np.ndarray) -> np.ndarray:
    return 0.5 * (a + np.swapaxes(a, -1, -2))


@dataclass(frozen=True)
class _Level:
    """One level of the reduction: its ``n`` blocks, the odd ones' ``d_inv`` (D_i^-1) and
    ``gab`` (n_odd, d, 2 d): ``[D_i^-1 A_i,i-1, D_i^-1 A_i,i+1]`` (zero past the end). Its
    transpose is the couplings to the neighbours times the pivot's inverse, ``[A_i-1,i;
    A_i+1,i] D_i^-1``: what the forward pass applies, so the couplings are not kept."""

    n: int
    d_inv: np.ndarray
    gab: np.ndarray

    @property
    def ga(self) -> np.ndarray:
        """``D_i^-1 A_i,i-1`` (n_odd, d, d)."""
        return self.gab[:, :, : self.gab.shape[1]]

    @property
    def gb(self) -> np.ndarray:
        """``D_i^-1 A_i,i+1`` (n_odd, d, d)."""
        return self.gab[:, :, self.gab.shape[1]:]


def _eliminate(D, U) -> tuple[list[_Level], np.ndarray]:
    """The block-tridiagonal matrix's reduction: its levels (the odd blocks eliminated, a
    level at a time) and the inverse (d, d) of the last block left."""
    levels = []
    while D.shape[0] > 1:
        n, d, _ = D.shape
        n_even, n_odd = (n + 1) // 2, n // 2
        b_left = U[0::2]
        b_right = U[1::2]
        if n % 2 == 0:
            b_right = np.concatenate([b_right, np.zeros((1, d, d))])
        couple = np.concatenate([b_left, np.swapaxes(b_right, 1, 2)], axis=1)
        d_inv = _spd_inv(D[1::2])
        gab = _bmm(d_inv, np.swapaxes(couple, 1, 2))  # [D_i^-1 A_i,i-1, D_i^-1 A_i,i+1]
        del couple  # (the level keeps gab alone)
        left = _bmm(b_left, gab)  # [A_i-1,i D_i^-1 A_i,i-1, A_i-1,i D_i^-1 A_i,i+1]
        d_e = D[0::2].copy()
        d_e[:n_odd] -= left[:, :, :d]
        d_e[1:] -= _bmm(np.swapaxes(b_right, 1, 2), gab[:, :, d:])[: n_even - 1]
        U = -left[: n_even - 1, :, d:]
        D = _sym(d_e)
        levels.append(_Level(n, d_inv, gab))
    return levels, _spd_inv(D)


def _forward(levels: list[_Level], h: np.ndarray, keep: bool = True, schur: bool = False):
    """The right-hand side ``h`` (K, d, m) through the reduction: the root's (1, d, m), each
    level's ``g = D_i^-1 h_i`` of its odd blocks (where ``keep``, for :func:`_back`) and,
    with ``schur``, ``sum_i h_i^T D_i^-1 h_i`` (m, m) over the odd blocks (with the root's,
    ``h^T A^-1 h``: the elimination is an ``L D L^T`` factorisation)."""
    gs = []
    T = np.zeros((h.shape[2], h.shape[2])) if schur else None
    for lev in levels:
        n_even, n_odd = (lev.n + 1) // 2, lev.n // 2
        h_o = np.ascontiguousarray(h[1::2])  # (for the products; tensordot would copy it)
        g = _bmm(lev.d_inv, h_o)
        if schur:
            T += np.tensordot(h_o, g, axes=([0, 1], [0, 1]))  # BLAS, not einsum's loop
        h_e = h[0::2].copy()
        # both neighbours' updates in one product: [A_i-1,i; A_i+1,i] D_i^-1 h_i
        step = _bmm(np.swapaxes(lev.gab, 1, 2), h_o)
        d = g.shape[1]
        h_e[:n_odd] -= step[:, :d]
        h_e[1:] -= step[: n_even - 1, d:]
        if keep:
            gs.append(g)
        h = h_e
    return h, gs, T


def _back(levels: list[_Level], S: np.ndarray, h: np.ndarray, gs: list) -> np.ndarray:
    """The solution (K, d, m) from the root's right-hand side ``h`` and the levels' ``g``
    (:func:`_forward`; taken from ``gs`` as they are used, so that their memory goes as the
    solution's comes), ``S`` the root's inverse."""
    if len(gs) != len(levels):
        raise ValueError(f"Expected {len(levels)} levels' right-hand sides, got {len(gs)}")
    x = S @ h
    for lev in reversed(levels):
        g = gs.pop()
        n = lev.n
        x_e = x if n % 2 else np.concatenate([x, np.zeros((1,) + x.shape[1:])])
        x_o = g - _bmm(lev.ga, x_e[:-1]) - _bmm(lev.gb, x_e[1:])
        x = np.empty((n,) + x_o.shape[1:])
        x[0::2] = x_e[: (n + 1) // 2]
        x[1::2] = x_o
    return x


def _inverse_blocks(levels: list[_Level], S: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The diagonal blocks (K, d, d) of ``A^-1`` and its blocks ``(A^-1)_k,k+1`` (K-1, d, d)
    from the reduction (``S`` the root's inverse): the recursion of interpolation/gp.py."""
    dim = S.shape[-1]
    C = np.zeros((0, dim, dim))
    for lev in reversed(levels):
        n, ga, gb = lev.n, lev.ga, lev.gb
        s_e, c_e = S, C
        if n % 2 == 0:
            s_e = np.concatenate([s_e, np.zeros((1, dim, dim))])
            c_e = np.concatenate([c_e, np.zeros((1, dim, dim))])
        # rows i (odd) of A Sigma = I with neighbours a = i-1, b = i+1
        s_ia = -(_bmm(ga, s_e[:-1]) + _bmm(gb, np.swapaxes(c_e, 1, 2)))
        s_ib = -(_bmm(ga, c_e) + _bmm(gb, s_e[1:]))
        s_ii = lev.d_inv - _bmm(ga, np.swapaxes(s_ia, 1, 2)) - _bmm(gb, np.swapaxes(s_ib, 1, 2))
        S = np.empty((n, dim, dim))
        S[0::2] = s_e[: (n + 1) // 2]
        S[1::2] = _sym(s_ii)
        C = np.empty((n - 1, dim, dim))
        C[0::2] = np.swapaxes(s_ia, 1, 2)
        C[1::2] = s_ib[: (n - 1) // 2]
    return S, C


def solve_bytes(K: int, d: int, G: int) -> int:
    """Bytes that one solve with covariances of ``K`` knots of ``d`` states and ``G``
    globals holds at its peak (:func:`solve_arrow` with ``overwrite``): the system's ``D``,
    ``U`` and ``B`` and the solve's own seven ``(K, d, d)`` and two ``(K, d, G)`` arrays
    (the reduction's levels, the right-hand side and its solution, the inverse's blocks and
    their temporaries; measured with tracemalloc in tests/test_joint.py). A run of the joint
    engine holds more (its measurements, the solution it keeps, other hypotheses'
    solutions): this is its floor (docs/joint.md#an-hours-floor)."""
    return 8 * int(K) * (9 * d * d + 3 * d * G)


def solve_arrow(system: ArrowSystem, want_cov: bool = False, overwrite: bool = False):
    """Solve an :class:`ArrowSystem` by eliminating the knots (with ``overwrite``, its
    ``D`` and ``U`` are scaled in place, not copied: the system is consumed but for ``a``,
    ``B``, ``C`` and ``c``).

    ``Y = A^-1 [a, B]``, ``S = C - B^T A^-1 B``, ``g = S^-1 (c - B^T A^-1 a)``,
    ``x = A^-1 a - A^-1 B g``. Returns an :class:`ArrowSolution`; its covariances are None
    without ``want_cov``, and then ``A^-1 B`` is not formed: ``B^T A^-1 B`` comes out of the
    reduction's forward pass and ``x`` from one more column, ``A^-1 (a - B g)``. The system
    is scaled by its diagonal first (Jacobi).
    """
    D, U, B, C = system.D, system.U, system.B, system.C
    K, d, _ = D.shape
    G = C.shape[0]
    sx = 1.0 / np.sqrt(np.einsum("kii->ki", D))
    sg = 1.0 / np.sqrt(np.diag(C)) if G else np.zeros(0)
    if overwrite:  # (the hour's two (K, d, d) copies not made)
        Ds, Us = D, U
        for sl in chunks(K):
            Ds[sl] *= sx[sl, :, None] * sx[sl, None, :]
        for sl in chunks(K - 1):
            Us[sl] *= sx[sl, :, None] * sx[sl.start + 1:sl.stop + 1, None, :]
    else:
        Ds = D * (sx[:, :, None] * sx[:, None, :])  # (one pass over the blocks)
        Us = U * (sx[:-1, :, None] * sx[1:, None, :])
    Cs = C * sg[:, None] * sg[None, :]
    rhs = np.empty((K, d, G + 1))
    rhs[:, :, 0] = system.a * sx
    np.multiply(B, sx[:, :, None], out=rhs[:, :, 1:])  # (no (K, d, G) array of scales)
    rhs[:, :, 1:] *= sg
    Bs = rhs[:, :, 1:]
    levels, S = _eliminate(Ds, Us)
    del Ds, Us  # (the levels hold what the passes need)
    if not want_cov:  # the Schur complement from the forward pass; one column back
        root, _, T = _forward(levels, rhs, keep=False, schur=True)
        T += np.tensordot(root, S @ root, axes=([0, 1], [0, 1]))  # [a, B]^T A^-1 [a, B]
        g = np.zeros(0)
        if G:
            g = _spd_inv(_sym(Cs - T[1:, 1:])) @ (system.c * sg - T[1:, 0])
        r = rhs[:, :, :1] - Bs @ g[:, None]
        root, gs, _ = _forward(levels, r)
        x = _back(levels, S, root, gs)[:, :, 0]
        return ArrowSolution(x * sx, g * sg, None, None, None)
    root, gs, _ = _forward(levels, rhs)
    Y = _back(levels, S, root, gs)
    ya, yb = Y[:, :, 0], Y[:, :, 1:]
    if G:
        T = np.tensordot(rhs, Y, axes=([0, 1], [0, 1]))  # [a, B]^T A^-1 [a, B], contiguous
        schur_inv = _spd_inv(_sym(Cs - T[1:, 1:]))
        g = schur_inv @ (system.c * sg - T[1:, 0])
        x = ya - yb @ g
    else:
        schur_inv, g, x = np.zeros((0, 0)), np.zeros(0), ya
    del rhs, Bs  # (the scaled B: its memory for the covariances')
    x, g = x * sx, g * sg
    var, var_next = _inverse_blocks(levels, S)
    del levels
    # L_k = -Y_B,k chol(S^-1) = -Sx yb_s chol(Ss^-1) (the globals' scale cancels), written
    # over yb in place, a few thousand knots at a time (no second (K, d, G) array)
    chol_s = np.linalg.cholesky(schur_inv) if G else np.zeros((0, 0))
    for sl in chunks(K):
        yb[sl] = -sx[sl, :, None] * (yb[sl] @ chol_s)
    var *= sx[:, :, None] * sx[:, None, :]
    var_next *= sx[:-1, :, None] * sx[1:, None, :]
    cov, nxt = var.copy(), np.concatenate([var_next, np.zeros((1, d, d))])
    for sl in chunks(K):  # L L^T a few thousand knots at a time
        lo, hi = sl.start, sl.stop
        cov[lo:hi] += _bmm(yb[lo:hi], np.swapaxes(yb[lo:hi], 1, 2))
        nxt[lo:hi - 1] += _bmm(yb[lo:hi - 1], np.swapaxes(yb[lo + 1:hi], 1, 2))
        if hi < K:
            nxt[hi - 1] += yb[hi - 1] @ yb[hi].T
    return ArrowSolution(x, g, cov, nxt[:-1], schur_inv * sg[:, None] * sg[None, :],
                         var, var_next, yb, sg[:, None] * chol_s)
