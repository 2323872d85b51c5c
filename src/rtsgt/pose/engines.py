"""The pose covariance engines, one class each, registered in :data:`ENGINES`.

An engine takes the valid poses of :func:`rtsgt.pose.estimate_poses` and their fits of the mean
inputs (:class:`PoseFits`) and returns the second moment and mean of the left perturbation of
the fit of perturbed inputs about them: :class:`MonteCarlo`, :class:`Unscented` (the unscented
transform) or :class:`Linear` (first order). Method, draws and threads: docs/pose.md.
"""

from __future__ import annotations

from collections import deque
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass
from typing import ClassVar

import numpy as np

from rtsgt.parallel import available_cores
from rtsgt.pose.registration import register, registration_jacobian, small_rotation_vector
from rtsgt.pose.weighted import newton_inverse_at, refine_batches, refine_samples

#: Registrations per Monte Carlo chunk by default (bounds the memory to ~10 MB).
DEFAULT_MC_CHUNK = 1 << 14
#: Threads of the Monte Carlo chunks when not given (None: :func:`mc_threads`).
MC_THREADS: int | None = None
#: The most threads the default takes.
MAX_MC_THREADS = 4


@dataclass(frozen=True)
class PoseFits:
    """The K valid poses of one call and their fits of the mean inputs.

    ``q`` (K, n, 3) world prisms, m; ``cov_q`` (K, 3n, 3n) their joint covariance; ``r``
    (n, 3) the reference, body frame; ``cov_r`` (3n, 3n); ``R`` (K, 3, 3), ``t`` (K, 3) the
    fits; ``gls``: the weighted fit's ``(W, J_q, J_r)``, shapes (K, 3n, 3n), (K, 6, 3n) twice,
    or None for the unweighted fit.
    """

    q: np.ndarray
    cov_q: np.ndarray
    r: np.ndarray
    cov_r: np.ndarray
    R: np.ndarray
    t: np.ndarray
    gls: tuple[np.ndarray, np.ndarray, np.ndarray] | None


def mc_threads(threads: int | None = None) -> int:
    """``threads`` if given, else :data:`MC_THREADS` if set, else the cores this process may
    run on, at most :data:`MAX_MC_THREADS`."""
    if threads is None:
        threads = MC_THREADS
    if threads is None:
        threads = min(available_cores(), MAX_MC_THREADS)
    if int(threads) != threads or threads < 1:
        raise ValueError(f"Expected a positive integer number of threads, got {threads}")
    return int(threads)


def perturbations(R: np.ndarray, t: np.ndarray, R0: np.ndarray, t0: np.ndarray) -> np.ndarray:
    """Left perturbations (..., S, 6) of fits ``R`` (..., S, 3, 3), ``t`` (..., S, 3) about
    ``R0`` (..., 3, 3), ``t0`` (..., 3)."""
    dR = R @ np.swapaxes(R0, -1, -2)[..., None, :, :]
    xi = np.empty(t.shape[:-1] + (6,))
    xi[..., :3] = t - t0[..., None, :]
    xi[..., 3:] = small_rotation_vector(dR)
    return xi


def fit_samples(P, Q, fits: PoseFits):
    """The fits of (K, S) perturbed problems: ``P`` body (may be broadcast), ``Q`` world,
    (K, S, n, 3). Unweighted: the closed form; weighted: Newton from each one's first-order
    prediction. Returns ``R`` (K, S, 3, 3), ``t`` (K, S, 3), the count of unconverged fits."""
    K, S, n, _ = Q.shape
    if fits.gls is None:
        Rs, ts = register(np.broadcast_to(P, Q.shape), Q)
        return Rs, ts, 0
    W, J_q, J_r = fits.gls
    dq = (Q - fits.q[:, None]).reshape(K, S, 3 * n)
    dr = (P - fits.r).reshape(P.shape[:-2] + (3 * n,))
    xi0 = dq @ np.swapaxes(J_q, 1, 2) + dr @ np.swapaxes(J_r, 1, 2)
    Rs, ts, conv, _ = refine_batches(P, Q, W, fits.R[:, None], fits.t[:, None], xi0)
    return Rs, ts, int(np.sum(~conv))


@dataclass(frozen=True)
class Linear:
    """First order: ``J_q Sigma_q J_q^T + J_r Sigma_r J_r^T`` with the fit's Jacobian."""

    name: ClassVar[str] = "linear"

    @classmethod
    def build(cls, **_) -> Linear:
        """The engine (it takes no arguments)."""
        return cls()

    def sample_count(self, n: int) -> None:
        """No samples."""
        return None

    def propagate(self, fits: PoseFits) -> tuple[np.ndarray, None, int]:
        """``(cov (K, 6, 6), None, 0)``."""
        K, n, _ = fits.q.shape
        if K == 0:
            return np.empty((0, 6, 6)), None, 0
        if fits.gls is None:
            J_q, J_r = registration_jacobian(np.broadcast_to(fits.r, fits.q.shape), fits.q,
                                             fits.R)
            Jq, Jr = J_q.reshape(K, 6, 3 * n), J_r.reshape(K, 6, 3 * n)
        else:
            Jq, Jr = fits.gls[1], fits.gls[2]
        c = Jq @ fits.cov_q @ np.swapaxes(Jq, 1, 2)
        return c + np.einsum("kai,ij,kbj->kab", Jr, fits.cov_r, Jr), None, 0


@dataclass(frozen=True)
class Unscented:
    """The unscented transform over ``(q_1..q_n, r_1..r_n)``: ``2 L`` sigma points,
    ``L = 6 n``, at ``+- sqrt(L)`` times the columns of the block factor, weights ``1 / 2L``."""

    name: ClassVar[str] = "ut"

    @classmethod
    def build(cls, **_) -> Unscented:
        """The engine (it takes no arguments)."""
        return cls()

    def sample_count(self, n: int) -> int:
        """The sigma points, ``12 n``."""
        return 12 * n

    def propagate(self, fits: PoseFits) -> tuple[np.ndarray, np.ndarray, int]:
        """``(cov (K, 6, 6), mean perturbation (K, 6), unconverged fits)``."""
        q, r = fits.q, fits.r
        K, n, _ = q.shape
        if K == 0:
            return np.empty((0, 6, 6)), np.empty((0, 6)), 0
        L = 6 * n
        gamma = np.sqrt(L)
        # row j of dq / dr: column j of the factor, moving the prisms / the reference
        dq = gamma * np.swapaxes(psd_factor(fits.cov_q), -1, -2).reshape(K, 3 * n, n, 3)
        q_sig = np.concatenate([q[:, None] + dq, q[:, None] - dq], axis=1)  # (K, 6n, n, 3)
        dr = gamma * psd_factor(fits.cov_r).T.reshape(3 * n, n, 3)
        r_sig = np.concatenate([r + dr, r - dr], axis=0)  # (6n, n, 3)
        p_sig_r = np.broadcast_to(r_sig, (K,) + r_sig.shape)
        P = np.concatenate([np.broadcast_to(r, q_sig.shape), p_sig_r], axis=1)
        Q = np.concatenate([q_sig, np.broadcast_to(q[:, None], p_sig_r.shape)], axis=1)
        Rs, ts, unconverged = fit_samples(P, Q, fits)
        xi = perturbations(Rs, ts, fits.R, fits.t)
        w = 1.0 / (2 * L)
        return w * np.einsum("kmi,kmj->kij", xi, xi), w * xi.sum(axis=1), unconverged


@dataclass(frozen=True)
class MonteCarlo:
    """``samples`` draws of every prism and of the reference (one per sample, shared by the
    poses) from ``rng``, each fitted; chunks of ``chunk_size`` fits on ``threads`` threads
    (default :func:`mc_threads`), the result the same bit for bit whatever their number."""

    rng: np.random.Generator
    samples: int = 1000
    chunk_size: int = DEFAULT_MC_CHUNK
    threads: int | None = None

    name: ClassVar[str] = "mc"

    def __post_init__(self) -> None:
        if not isinstance(self.rng, np.random.Generator):
            raise ValueError(f"Expected a numpy.random.Generator for engine 'mc', "
                             f"got {self.rng!r}")
        if int(self.samples) != self.samples or self.samples < 2:
            raise ValueError(f"Expected an integer number of samples >= 2, got {self.samples}")
        object.__setattr__(self, "samples", int(self.samples))
        object.__setattr__(self, "threads", mc_threads(self.threads))
        if int(self.chunk_size) < 1:
            raise ValueError(f"Expected a positive chunk_size, got {self.chunk_size}")

    @classmethod
    def build(cls, *, rng=None, samples=1000, chunk_size=None, threads=None, **_) -> MonteCarlo:
        """The engine from :func:`rtsgt.pose.estimate_poses`'s arguments (``chunk_size`` None:
        :data:`DEFAULT_MC_CHUNK`)."""
        return cls(rng, samples, DEFAULT_MC_CHUNK if chunk_size is None else chunk_size, threads)

    def sample_count(self, n: int) -> int:
        """The samples ``M``."""
        return self.samples

    def propagate(self, fits: PoseFits) -> tuple[np.ndarray, np.ndarray, int]:
        """``(cov (K, 6, 6), mean perturbation (K, 6), unconverged fits)``. Draws: the
        reference (M, 3n) first (even with no pose), then the prisms (K, M, n, 3) in order."""
        n = fits.r.shape[0]
        M = self.samples
        z_r = self.rng.standard_normal((M, 3 * n)) @ psd_factor(fits.cov_r).T
        K = fits.q.shape[0]
        if K == 0:
            return np.empty((0, 6, 6)), np.empty((0, 6)), 0
        r_samples = (fits.r.reshape(3 * n) + z_r).reshape(M, n, 3)
        cov = np.empty((K, 6, 6))
        off = np.empty((K, 6))
        work = _mc_work(fits, psd_factor(fits.cov_q), r_samples, cov, off)
        per = max(1, int(self.chunk_size) // M)

        def draws():  # (s, e, z) in chunk order, each drawn when asked for
            for s in range(0, K, per):
                e = min(K, s + per)
                yield s, e, self.rng.standard_normal((e - s, M, n, 3)).reshape(e - s, M, 3 * n)

        threads = min(self.threads, len(range(0, K, per)))
        if threads <= 1:
            return cov, off, sum(work(*chunk) for chunk in draws())
        return cov, off, _on_threads(work, draws(), threads)


def _mc_work(fits: PoseFits, Lq: np.ndarray, r_samples: np.ndarray, cov: np.ndarray,
             off: np.ndarray):
    """The fit of one chunk of Monte Carlo poses: ``work(s, e, z)`` fits poses ``[s, e)`` from
    their draws ``z`` (e - s, M, 3n), fills ``cov`` and ``off`` there and returns the count of
    unconverged fits. ``Lq`` (K, 3n, 3n) factors the prisms' joint covariance."""
    q, r, R0, t0, gls = fits.q, fits.r, fits.R, fits.t, fits.gls
    K, n, _ = q.shape
    M = r_samples.shape[0]
    if gls is None:
        def work(s: int, e: int, z: np.ndarray) -> int:
            qs = q[s:e, None] + np.einsum("kab,kmb->kma", Lq[s:e], z).reshape(e - s, M, n, 3)
            Rs, ts = register(np.broadcast_to(r_samples[None], qs.shape), qs)
            xi = perturbations(Rs, ts, R0[s:e], t0[s:e])
            cov[s:e] = np.einsum("kmi,kmj->kij", xi, xi) / M
            off[s:e] = xi.mean(axis=1)
            return 0
        return work
    W, J_q, J_r = gls
    X = np.ascontiguousarray(np.moveaxis(r_samples, 0, -1))  # (n, 3, M)
    dr = np.ascontiguousarray((r_samples - r).reshape(M, 3 * n).T)  # (3n, M)
    shifted = (q - t0[:, None, :]).reshape(K, 3 * n, 1)

    def work(s: int, e: int, z: np.ndarray) -> int:
        u = 0
        dq = Lq[s:e] @ np.swapaxes(z, 1, 2)  # (k, 3n, M)
        xi0 = J_q[s:e] @ dq + J_r[s:e] @ dr  # first-order prediction
        Wt, P, N_inv = newton_inverse_at(np.broadcast_to(r, q[s:e].shape), q[s:e], W[s:e],
                                         R0[s:e], t0[s:e])
        xi, conv = refine_samples(shifted[s:e] + dq, X, Wt, P, N_inv, R0[s:e], xi0)
        if not conv.all():  # far samples: Newton's steps from their first-order prediction
            kk, mm = np.nonzero(~conv)
            pb = r_samples[mm][:, None]
            qb = (q[s + kk] + np.swapaxes(dq, 1, 2)[kk, mm].reshape(-1, n, 3))[:, None]
            Rb, tb, cb, _ = refine_batches(pb, qb, W[s + kk], R0[s + kk, None],
                                           t0[s + kk, None], xi0[kk, :, mm][:, None])
            xi[kk, :, mm] = perturbations(Rb, tb, R0[s + kk], t0[s + kk])[:, 0]
            u += int(np.sum(~cb))
        cov[s:e] = xi @ np.swapaxes(xi, 1, 2) / M
        off[s:e] = xi.mean(axis=2)
        return u
    return work


def _on_threads(work, chunks, threads: int) -> int:
    """Run ``work(*chunk)`` for each of ``chunks`` on a pool of ``threads`` threads, the chunks
    drawn on the calling thread in order, at most ``threads + 1`` alive; the summed results."""
    unconverged = 0
    pending: deque[Future] = deque()
    with ThreadPoolExecutor(max_workers=threads, thread_name_prefix="rtsgt-pose-mc") as pool:
        try:
            for chunk in chunks:
                pending.append(pool.submit(work, *chunk))
                del chunk
                while len(pending) > threads:  # threads running, one queued, one drawing
                    unconverged += pending.popleft().result()
            while pending:
                unconverged += pending.popleft().result()
        finally:
            for f in pending:
                f.cancel()
    return unconverged


def psd_factor(cov) -> np.ndarray:
    """``L`` (..., d, d) with ``L L^T = cov`` (..., d, d): Cholesky, or for a singular batch
    ``V diag(sqrt(max(w, 0)))`` scaling the eigenvectors' *columns*
    (docs/noise-model.md#reference-code-pitfalls)."""
    cov = np.asarray(cov, dtype=float)
    try:
        return np.linalg.cholesky(cov)
    except np.linalg.LinAlgError:
        w, V = np.linalg.eigh(0.5 * (cov + np.swapaxes(cov, -1, -2)))
        return V * np.sqrt(np.clip(w, 0.0, None))[..., None, :]


#: The engines by the name options, commands and files use.
ENGINES: dict[str, type] = {e.name: e for e in (MonteCarlo, Unscented, Linear)}
