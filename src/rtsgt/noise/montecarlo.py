"""Monte Carlo engine of the per-measurement noise model (the paper's method, vectorised).

Samples of every measurement as (n, M) arrays in chunks of about :data:`CHUNK_ELEMENTS`, each
chunk from a child generator of the run's (reproducible whatever the threads); the total and
each source alone share the draws; samples are displacements from the nominal point (float32
safe); one-direction sources are reduced exactly. docs/noise-model.md#monte-carlo.
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from typing import NamedTuple

import numpy as np

from rtsgt.errors import InputError
from rtsgt.geometry.so3 import exp_so3
from rtsgt.measurement.atmosphere import (
    KELVIN,
    P0_HPA,
    WATER_VAPOUR_COEFF,
    group_refractivity,
    refractivity,
)
from rtsgt.noise.model import NoiseModel, Nominal

#: Target number of measurement-samples per chunk (n * M); the workspace holds 28 arrays of
#: this size (7 MB in float32, 14 MB in float64), and memory stays bounded whatever the number
#: of measurements. Larger chunks spill out of the caches, smaller ones pay more Python
#: overhead per sample (2**15 costs about 7 % more CPU time on the benchmark).
CHUNK_ELEMENTS = 2**16

#: Perturbations up to this size (rad) use the Taylor form of sin / cos (exact in float64).
_TAYLOR_LIMIT = 2e-4

_LN10 = np.log(10.0)


def sample_gaussian(cov: np.ndarray, n_samples: int, rng: np.random.Generator) -> np.ndarray:
    """(n_samples, k) zero-mean Gaussian draws of covariance ``cov`` (k, k), positive
    semi-definite, by its symmetric square root (docs/noise-model.md#reference-code-pitfalls)."""
    cov = np.asarray(cov, dtype=float)
    w, V = np.linalg.eigh(0.5 * (cov + cov.T))
    L = V * np.sqrt(np.clip(w, 0.0, None))[None, :]
    z = rng.standard_normal((int(n_samples), cov.shape[0]))
    return z @ L.T


def transform_samples(
    T_world_station, n_samples: int, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray] | None:
    """The ``n_samples`` transform samples ``(R (M, 3, 3), t (M, 3))`` of the calibration
    source: the transform's own first ones (sample m of every measurement uses sample m), else
    drawn from its 6x6 covariance (left perturbation), else None
    (docs/noise-model.md#extrinsic-calibration). Raises :class:`InputError` when it carries
    fewer than ``n_samples``."""
    if T_world_station is None:
        return None
    Rs = T_world_station.samples_rotation
    ts = T_world_station.samples_translation
    if Rs is not None and ts is not None:
        Rs = np.asarray(Rs, dtype=float)
        ts = np.asarray(ts, dtype=float)
        if Rs.shape[0] < n_samples or ts.shape[0] < n_samples:
            raise InputError(
                f"The transform {T_world_station.frame_to} <- {T_world_station.frame_from} "
                f"carries {min(Rs.shape[0], ts.shape[0])} Monte Carlo samples, fewer than the "
                f"{n_samples} requested: calibrate with at least as many samples, or lower "
                "samples"
            )
        return Rs[:n_samples], ts[:n_samples]
    if T_world_station.covariance is None:
        return None
    xi = sample_gaussian(T_world_station.covariance, n_samples, rng)
    R = exp_so3(xi[:, 3:]) @ T_world_station.rotation
    t = T_world_station.translation + xi[:, :3]
    return R, t


def calibration_covariance_from_samples(
    p_station: np.ndarray, Rs: np.ndarray, ts: np.ndarray
) -> np.ndarray:
    """(N, 3, 3) sample covariance (ddof 1) of ``R_m p + t_m`` over the samples ``Rs``
    (M, 3, 3), ``ts`` (M, 3) for each point ``p_station`` (N, 3): ``A(p) C A(p)^T`` with ``C``
    the 12x12 sample covariance of ``(vec R_m, t_m)``, the map being linear in them."""
    M = Rs.shape[0]
    X = np.concatenate([Rs.reshape(M, 9), ts], axis=1)
    X = X - X.mean(axis=0)
    C = X.T @ X / (M - 1)
    Crr = C[:9, :9].reshape(3, 3, 3, 3)
    Crt = C[:9, 9:].reshape(3, 3, 3)
    Ctt = C[9:, 9:]
    p = p_station
    out = np.einsum("nj,ijkl,nl->nik", p, Crr, p, optimize=True)
    cross = np.einsum("nj,ijk->nik", p, Crt, optimize=True)
    out += cross + np.swapaxes(cross, -1, -2) + Ctt
    return out


class _BufferGroup(NamedTuple):
    """Named (n, M) buffers of the workspace that play one role (internal)."""

    names: tuple[str, ...]
    doc: str


#: The workspace's buffers, by role (allocation order: the order of :attr:`_Workspace.NAMES`).
_BUFFER_GROUPS = {
    "normals": _BufferGroup(
        ("z0", "z1", "z2", "z3"),
        "Standard normal draws, scaled in place into the errors: ``z0`` e_d (distance, m), "
        "``z1`` e_V and ``z2`` e_H (angles, rad) of ``instrument``; ``z3`` e_t of ``tilt``.",
    ),
    "uniforms": _BufferGroup(
        ("u0", "u1", "u2"),
        "U[0, 1) draws of temperature, pressure, humidity for ``atmosphere``, overwritten by "
        ":func:`_alpha_samples` (``u1`` holds the alpha samples afterwards); before them, the "
        "float32 Box-Muller of :func:`_standard_normals` uses ``u0``, ``u1`` as scratch.",
    ),
    "time_sync": _BufferGroup(
        ("ts",), "``ts``: the signed time-synchronisation error e_ts (s) of ``time_sync``."
    ),
    "scratch": _BufferGroup(
        ("a", "b"),
        "Short-lived temporaries of every step (``a`` also takes the uniforms of the sign "
        "of e_ts).",
    ),
    "vertical": _BufferGroup(
        ("dsv", "dcv", "sv", "cv"),
        "Perturbed V: ``sin V^ - sin V``, ``cos V^ - cos V``, ``sin V^``, ``cos V^``.",
    ),
    "tilt_hz": _BufferGroup(
        ("tl",), "``tl``: the Hz perturbation ``e_t cot V^`` (plus the other one, if any)."
    ),
    "horizontal": _BufferGroup(
        ("dsh", "dch", "sh", "ch"),
        "Perturbed Hz: ``sin Hz^ - sin Hz``, ``cos Hz^ - cos Hz``, ``sin Hz^``, ``cos Hz^``.",
    ),
    "distances": _BufferGroup(
        ("dr", "dd"),
        "``dr``: horizontal distance ``r^ - r0``; ``dd``: corrected slope distance "
        "``d^ - d0``.",
    ),
    "station": _BufferGroup(
        ("x", "y", "z"), "Station-frame displacement samples (the output of :func:`_deltas`)."
    ),
    "world": _BufferGroup(
        ("wx", "wy", "wz"),
        "World-frame displacement samples of the total with calibration samples; ``wx`` "
        "holds ``dV = e_V + e_t`` before that.",
    ),
}


class _Workspace:
    """Scratch arrays of shape (n, M) reused from chunk to chunk (internal).

    Allocating fresh half-megabyte temporaries for every operation costs page faults that
    double the run time; every (n, M) operation of the engine writes into these buffers with
    ``out=`` instead. The last, shorter chunk uses the leading rows (views stay contiguous).
    Every buffer is a plain attribute (``ws.z0``, ...); :data:`_BUFFER_GROUPS` says what each
    holds. ``mask`` is a boolean (n, M) buffer (the sign of e_ts).
    """

    NAMES = tuple(name for group in _BUFFER_GROUPS.values() for name in group.names)

    def __init__(self, n: int, M: int, dtype):
        self.n_max = n
        self.dtype = dtype
        self._bufs = {k: np.empty((n, M), dtype=dtype) for k in self.NAMES}
        self._mask = np.empty((n, M), dtype=bool)
        self.n = -1
        self.rows(n)

    def rows(self, n: int) -> None:
        """Use the first ``n`` rows: every name becomes a plain attribute (an (n, M) view)."""
        if n != self.n:
            self.n = n
            for k, buf in self._bufs.items():
                setattr(self, k, buf[:n])
            self.mask = self._mask[:n]


def _standard_normals(ws: _Workspace, rng: np.random.Generator, outs) -> None:
    """Fill each array of ``outs`` (views of the workspace) with standard normal draws.

    float64: ``Generator.standard_normal`` (ziggurat). float32: the Box-Muller transform of
    ``Generator.random`` float32 uniforms, ``r = sqrt(-2 ln(1 - u1))``, ``z = (r cos 2 pi u2,
    r sin 2 pi u2)`` (Box & Muller 1958), which numpy's SIMD float32 ``log`` / ``sin`` / ``cos``
    make about 1.5 times faster than the float32 ziggurat. The 24-bit uniforms bound
    ``|z| <= 5.8``: the tails beyond carry 7e-9 of the probability and change a variance by
    less than 1e-6 (relative), far below the Monte Carlo error. Uses ``ws.u0``, ``ws.u1``.
    """
    if ws.dtype == np.float64:
        for o in outs:
            rng.standard_normal(out=o, dtype=np.float64)
        return
    f32 = np.float32
    for i in range(0, len(outs), 2):
        pair = outs[i:i + 2]
        r, th = ws.u0, ws.u1
        rng.random(out=r, dtype=f32)
        rng.random(out=th, dtype=f32)
        np.subtract(f32(1.0), r, out=r)  # (0, 1]
        np.log(r, out=r)
        r *= f32(-2.0)
        np.sqrt(r, out=r)
        th *= f32(2.0 * np.pi)
        np.cos(th, out=pair[0])
        pair[0] *= r
        if len(pair) == 2:
            np.sin(th, out=pair[1])
            pair[1] *= r


def _sincos_delta(ws: _Workspace, trig, delta, ds, dc):
    """``ds = sin(a + delta) - sin a``, ``dc = cos(a + delta) - cos a`` (into ``ds``, ``dc``).

    From ``trig = (sin a, cos a, sin(a) / 2, -cos(a) / 2, -sin a)`` (n, 1) columns (the last
    three save operations) by the addition theorem, with ``sin(delta)`` and ``1 - cos(delta)``
    by their Taylor series truncated where the next term is below the rounding error of the
    working precision for ``|delta| <= 2e-4`` rad (41 arc seconds): float64 uses
    ``delta (1 - delta^2 / 6)`` and ``delta^2 / 2 (1 - delta^2 / 12)`` (next terms below 1e-17
    relative), float32 ``delta`` and ``delta^2 / 2``. Larger perturbations use
    ``np.sin(delta)`` and ``2 sin^2(delta / 2)``. Uses ``ws.a`` and ``ws.b`` as scratch.
    """
    a, b = ws.a, ws.b
    s0, c0, hs0, nhc0, ns0 = trig
    if delta.max() <= _TAYLOR_LIMIT and delta.min() >= -_TAYLOR_LIMIT:
        np.multiply(delta, delta, out=a)  # d2
        if ws.dtype == np.float32:
            # ds = c0 d - (s0 / 2) d2, dc = (-c0 / 2) d2 + (-s0) d: seven passes
            np.multiply(c0, delta, out=ds)
            np.multiply(hs0, a, out=dc)
            ds -= dc
            np.multiply(nhc0, a, out=dc)
            np.multiply(ns0, delta, out=a)
            dc += a
            return
        np.multiply(a, -1.0 / 6.0, out=b)
        b += 1.0
        b *= delta  # sd = d (1 - d2 / 6)
        sd = b
        np.multiply(a, -1.0 / 12.0, out=dc)
        dc += 1.0
        dc *= a
        dc *= 0.5  # omc = d2 / 2 (1 - d2 / 12), held in dc
    else:
        sd = np.sin(delta, out=b)
        np.multiply(delta, 0.5, out=dc)  # 1 - cos d = 2 sin^2(d / 2), without cancellation
        np.sin(dc, out=dc)
        np.multiply(dc, dc, out=dc)
        dc *= 2.0
    # omc = 1 - cos d is in dc:
    # sin(a + d) - sin a = c0 sin d - s0 (1 - cos d)
    # cos(a + d) - cos a = -(s0 sin d + c0 (1 - cos d)) = (-c0) omc + (-s0) sin d
    np.multiply(c0, sd, out=ds)
    np.multiply(s0, dc, out=a)
    ds -= a
    np.multiply(nhc0, dc, out=dc)
    dc += dc  # -c0 omc
    np.multiply(ns0, sd, out=a)
    dc += a


_PAIRS = ((0, 0), (1, 1), (2, 2), (0, 1), (0, 2), (1, 2))


def _cov_rows(x, y, z) -> np.ndarray:
    """Sample covariance (ddof = 1) of (n, M) arrays per row -> (n, 3, 3) float64.

    Row dot products by ``matmul`` of (n, 1, M) by (n, M, 1) stacks (BLAS dots: three times
    faster than centring and ``einsum``, and accumulated more accurately): the sums ``s`` and
    the products ``G`` give ``(G - s s^T / M) / (M - 1)`` in float64. The samples are
    displacements from the nominal point, whose mean is far below their spread, so the
    subtraction cancels nothing; were a row's mean comparable to its spread, the rows are
    centred first (``x``, ``y``, ``z`` are scratch buffers, modified then).
    """
    n, M = x.shape
    X = (x, y, z)
    ones = np.ones((M, 1), dtype=x.dtype)
    s = np.empty((n, 3))
    for i, a in enumerate(X):
        s[:, i] = np.matmul(a, ones)[:, 0]
    mean = s / M
    rows = [a[:, None, :] for a in X]
    cols = [a[:, :, None] for a in X]
    out = np.empty((n, 3, 3))
    for i, j in _PAIRS:
        out[:, i, j] = np.matmul(rows[i], cols[j])[:, 0, 0]
    if np.any(M * mean**2 > 0.01 * np.diagonal(out, axis1=1, axis2=2)):
        for i, a in enumerate(X):  # mean >= 0.1 rms: centre first (never for displacements)
            a -= mean[:, i:i + 1].astype(a.dtype)
            s[:, i] = np.matmul(a, ones)[:, 0]
        for i, j in _PAIRS:
            out[:, i, j] = np.matmul(rows[i], cols[j])[:, 0, 0]
    for i, j in _PAIRS:
        out[:, i, j] -= s[:, i] * s[:, j] / M
        out[:, j, i] = out[:, i, j]
    out /= M - 1
    return out


def _var_rows(a) -> np.ndarray:
    """Sample variance (ddof = 1) of an (n, M) array per row (``a`` is not modified)."""
    mean = a.mean(axis=1, keepdims=True, dtype=np.float64)
    # E[(a - m)^2] = E[a^2] - m^2 would cancel; centre instead (one temporary per call)
    ac = a - mean.astype(a.dtype)
    return np.einsum("nm,nm->n", ac, ac).astype(float) / (a.shape[1] - 1)


def _outer(u) -> np.ndarray:
    return u[:, :, None] * u[:, None, :]


class _Chunk:
    """Nominal columns (n, 1) of one chunk, in the working dtype (internal)."""

    def __init__(self, nom: Nominal, model: NoiseModel, sl: slice, dtype):
        prof = model.instrument
        self.model = model
        self.dtype = dtype
        def col(a, take=True):
            return np.ascontiguousarray(a[sl] if take else a, dtype=dtype)[:, None]

        sh, chz = np.sin(nom.hz[sl]), np.cos(nom.hz[sl])
        sv, cv = np.sin(nom.v[sl]), np.cos(nom.v[sl])
        self.hz_s, self.hz_c = col(sh, False), col(chz, False)
        self.v_s, self.v_c = col(sv, False), col(cv, False)
        # (sin, cos, sin / 2, -cos / 2, -sin) of the nominal angles, for _sincos_delta
        self.trig_hz = (self.hz_s, self.hz_c, col(0.5 * sh, False), col(-0.5 * chz, False),
                        col(-sh, False))
        self.trig_v = (self.v_s, self.v_c, col(0.5 * sv, False), col(-0.5 * cv, False),
                       col(-sv, False))
        self.u_los = np.stack([sv * sh, sv * chz, cv], axis=1)  # float64, (n, 3)
        self.d = col(nom.d)
        self.d64 = nom.d[sl]
        self.d0 = col(nom.d_corr)
        self.r0 = col(nom.d_corr[sl] * sv, False)  # horizontal distance
        self.p0 = np.ascontiguousarray(nom.xyz_station[sl], dtype=dtype)
        self.one_alpha0 = col(1.0 + 1e-6 * nom.ppm)
        self.alpha0 = col(1e-6 * nom.ppm)
        self.sig_d = col(prof.sigma_distance(nom.d))
        h_t, h_p, h_r = (model.temperature_halfwidth_c, model.pressure_halfwidth_hpa,
                         model.humidity_halfwidth_pct)
        # T^ = T + h (2u - 1) = (T - h) + 2h u with u ~ U[0, 1)
        self.T_lo, self.T_w = col(nom.temperature_c - h_t), dtype(2.0 * h_t)
        self.p_lo, self.p_w = col(nom.pressure_hpa - h_p), dtype(2.0 * h_p)
        self.rh_lo, self.rh_w = col(nom.humidity_pct - h_r), dtype(2.0 * h_r)
        self.vel64 = nom.velocity[sl]
        self.vel = np.ascontiguousarray(self.vel64, dtype=dtype)


def _atmosphere_constants(model: NoiseModel) -> tuple[float, float]:
    """``(N_gr, N_REF)`` of the instrument's wavelength and reference atmosphere, from
    :mod:`rtsgt.measurement.atmosphere` (the constants :func:`_alpha_samples` takes)."""
    prof = model.instrument
    n_gr = float(group_refractivity(prof.wavelength_um))
    n_ref = float(refractivity(
        prof.reference_temperature_c, prof.reference_pressure_hpa, prof.reference_humidity_pct,
        prof.wavelength_um, model.vapour_formula,
    ))
    return n_gr, n_ref


def _alpha_samples(ws: _Workspace, ch: _Chunk, n_gr: float, n_ref: float):
    """``alpha = 1e-6 K`` at the perturbed weather into ``ws.u1`` (returned), from the U[0, 1)
    draws of temperature, pressure, humidity in ``ws.u0``, ``ws.u1``, ``ws.u2`` (overwritten):
    :func:`rtsgt.measurement.atmosphere.correction_ppm` in place, in the working dtype
    (docs/noise-model.md#monte-carlo)."""
    dt = ws.dtype
    model = ch.model
    t, p, rh, E = ws.u0, ws.u1, ws.u2, ws.a
    t *= ch.T_w
    t += ch.T_lo
    p *= ch.p_w
    p += ch.p_lo
    rh *= ch.rh_w
    rh += ch.rh_lo
    np.clip(rh, 0.0, 100.0, out=rh)
    if model.vapour_formula == "magnus":
        # [MAG] E = 6.1078 10^(7.5 t / (237.3 + t))
        np.add(t, dt(237.3), out=E)
        np.divide(t, E, out=E)
        E *= dt(_LN10 * 7.5)
        np.exp(E, out=E)
        E *= dt(6.1078)
    else:
        # [BUCK] E = (1.0007 + 3.46e-6 p) 6.1121 exp(17.502 t / (240.94 + t))
        np.add(t, dt(240.94), out=E)
        np.divide(t, E, out=E)
        E *= dt(17.502)
        np.exp(E, out=E)
        np.multiply(p, dt(3.46e-6 * 6.1121), out=ws.b)
        ws.b += dt(1.0007 * 6.1121)
        E *= ws.b
    # [IAG99-2] N_L = (273.15/1013.25 N_gr p - 11.27 RH/100 E) / T
    E *= rh
    E *= dt(WATER_VAPOUR_COEFF / 100.0)
    n_l = p
    n_l *= dt(KELVIN / P0_HPA * n_gr)
    n_l -= E
    t += dt(KELVIN)
    n_l /= t
    # [R02-K] K = (N_REF - N_L) / (1 + 1e-6 N_L); alpha = 1e-6 K
    den = ws.b
    np.multiply(n_l, dt(1e-6), out=den)
    den += dt(1.0)
    np.subtract(dt(n_ref), n_l, out=n_l)
    n_l /= den
    n_l *= dt(1e-6)
    return n_l


def _deltas(ws: _Workspace, ch: _Chunk, dd, dV, e_t, dH):
    """Sample displacements from the nominal station-frame position, into ws.x, ws.y, ws.z.

    ``dd``: perturbation of the corrected slope distance (None: none); ``dV``: total
    perturbation of V; ``e_t``: tilt error, entering Hz through ``cot(V^)``; ``dH``: the other
    perturbation of Hz (None: none). Exact algebra, no cancellation:
    ``r^ - r0 = dd sV^ + d0 dsV``, ``x^ - x0 = (r^ - r0) sH^ + r0 dsH``,
    ``y^ - y0 = (r^ - r0) cH^ + r0 dcH``, ``z^ - z0 = dd cV^ + d0 dcV``.
    """
    x, y, z, a = ws.x, ws.y, ws.z, ws.a
    if dV is None:
        dsV = dcV = None
        sV, cV = ch.v_s, ch.v_c
    else:
        dsV, dcV = ws.dsv, ws.dcv
        _sincos_delta(ws, ch.trig_v, dV, dsV, dcV)
        sV = np.add(dsV, ch.v_s, out=ws.sv)
        cV = np.add(dcV, ch.v_c, out=ws.cv)
    if e_t is not None:
        tl = np.multiply(e_t, cV, out=ws.tl)
        tl /= sV  # e_t cot(V^)
        if dH is not None:
            tl += dH
        dH = tl
    if dH is None:
        dsH = dcH = None
        sH, cH = ch.hz_s, ch.hz_c
    else:
        dsH, dcH = ws.dsh, ws.dch
        _sincos_delta(ws, ch.trig_hz, dH, dsH, dcH)
        sH = np.add(dsH, ch.hz_s, out=ws.sh)
        cH = np.add(dcH, ch.hz_c, out=ws.ch)
    dr = ws.dr
    if dd is None:
        if dsV is None:
            dr[...] = 0.0
            z[...] = 0.0
        else:
            np.multiply(ch.d0, dsV, out=dr)
            np.multiply(ch.d0, dcV, out=z)
    else:
        np.multiply(dd, sV, out=dr)
        np.multiply(dd, cV, out=z)
        if dsV is not None:
            dr += np.multiply(ch.d0, dsV, out=a)
            z += np.multiply(ch.d0, dcV, out=a)
    np.multiply(dr, sH, out=x)
    np.multiply(dr, cH, out=y)
    if dsH is not None:
        x += np.multiply(ch.r0, dsH, out=a)
        y += np.multiply(ch.r0, dcH, out=a)
    return x, y, z


def _run_chunk(
    ws: _Workspace, ch: _Chunk, rng: np.random.Generator, cal: tuple | None,
    n_gr: float, n_ref: float,
) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """Monte Carlo of one chunk: total (world frame when ``cal`` is given, else station frame)
    and per-source covariances (station frame; calibration handled by the caller)."""
    x, y, z, by_source = _sample_chunk(ws, ch, rng, cal, n_gr, n_ref)
    return _cov_rows(x, y, z), by_source


class _Draws(NamedTuple):
    """The errors of one chunk, (n, M) views of the workspace (None: source off)."""

    e_d: np.ndarray | None  # instrument: slope distance (m)
    e_V: np.ndarray | None  # instrument: vertical angle (rad)
    e_H: np.ndarray | None  # instrument: horizontal angle (rad)
    e_t: np.ndarray | None  # tilt (rad)
    e_ts: np.ndarray | None  # time_sync (s)
    alpha: np.ndarray | None  # atmosphere: 1e-6 K at the perturbed weather


def _draw_errors(
    ws: _Workspace, ch: _Chunk, rng: np.random.Generator, n_gr: float, n_ref: float
) -> _Draws:
    """Draw the errors of every active source, in a fixed order (the order of the draws
    fixes the result for a seed): the normals of ``instrument`` and ``tilt``, then
    ``time_sync``, then the uniforms of ``atmosphere``."""
    model = ch.model
    prof = model.instrument
    srcs = model.sources
    dt = ws.dtype
    e_d = e_V = e_H = e_t = None
    normals = []
    if "instrument" in srcs:
        e_d, e_V, e_H = ws.z0, ws.z1, ws.z2
        normals += [e_d, e_V, e_H]
    if "tilt" in srcs:
        e_t = ws.z3
        normals.append(e_t)
    _standard_normals(ws, rng, normals)
    if e_d is not None:
        e_d *= ch.sig_d
        e_V *= dt(prof.sigma_angle)
        e_H *= dt(prof.sigma_angle)
    if e_t is not None:
        e_t *= dt(prof.sigma_tilt)
    e_ts = None
    if "time_sync" in srcs:
        e_ts = ws.ts
        _standard_normals(ws, rng, [e_ts])
        e_ts *= dt(model.time_sync_std_s)
        e_ts += dt(model.time_sync_mean_s)
        flip = rng.random(out=ws.a, dtype=dt)
        np.less(flip, 0.5, out=ws.mask)
        np.negative(e_ts, out=e_ts, where=ws.mask)
    # after the normals: the float32 Box-Muller of _standard_normals overwrites u0, u1
    alpha = None
    if "atmosphere" in srcs:
        for buf in (ws.u0, ws.u1, ws.u2):
            rng.random(out=buf, dtype=dt)
        alpha = _alpha_samples(ws, ch, n_gr, n_ref)
    return _Draws(e_d, e_V, e_H, e_t, e_ts, alpha)


def _single_source_covariances(
    ws: _Workspace, ch: _Chunk, draws: _Draws
) -> dict[str, np.ndarray]:
    """Station-frame covariance of each source alone (calibration excepted): by sampling for
    ``instrument`` and ``tilt``, by the exact one-direction reductions for ``atmosphere`` and
    ``time_sync``. Leaves the draws unchanged."""
    srcs = ch.model.sources
    by_source: dict[str, np.ndarray] = {}
    if "instrument" in srcs:
        dd = np.multiply(draws.e_d, ch.one_alpha0, out=ws.dd)
        by_source["instrument"] = _cov_rows(*_deltas(ws, ch, dd, draws.e_V, None, draws.e_H))
    if "tilt" in srcs:
        by_source["tilt"] = _cov_rows(*_deltas(ws, ch, None, draws.e_t, draws.e_t, None))
    if "atmosphere" in srcs:
        var = _var_rows(draws.alpha) * ch.d64**2
        by_source["atmosphere"] = _outer(ch.u_los) * var[:, None, None]
    if "time_sync" in srcs:
        by_source["time_sync"] = _outer(ch.vel64) * _var_rows(draws.e_ts)[:, None, None]
    return by_source


def _total_displacements(
    ws: _Workspace, ch: _Chunk, draws: _Draws
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Station-frame displacement samples of all the sources together, into ws.x, ws.y, ws.z
    (``draws.alpha`` is overwritten)."""
    dt = ws.dtype
    e_d, e_V, e_H, e_t, e_ts, alpha = draws
    dV = None
    if e_V is not None and e_t is not None:
        dV = np.add(e_V, e_t, out=ws.wx)  # wx is only used after _deltas
    elif e_V is not None:
        dV = e_V
    elif e_t is not None:
        dV = e_t
    # dd = (d + e_d)(1 + alpha) - d (1 + alpha0) = e_d (1 + alpha) + d (alpha - alpha0)
    dd = None
    if alpha is not None:
        dd = np.subtract(alpha, ch.alpha0, out=ws.dd)
        dd *= ch.d
        if e_d is not None:
            alpha += dt(1.0)
            alpha *= e_d
            dd += alpha
    elif e_d is not None:
        dd = np.multiply(e_d, ch.one_alpha0, out=ws.dd)
    x, y, z = _deltas(ws, ch, dd, dV, e_t, e_H)
    if e_ts is not None:
        x += np.multiply(e_ts, ch.vel[:, 0:1], out=ws.a)
        y += np.multiply(e_ts, ch.vel[:, 1:2], out=ws.a)
        z += np.multiply(e_ts, ch.vel[:, 2:3], out=ws.a)
    return x, y, z


def _to_world_samples(
    ws: _Workspace, ch: _Chunk, cal: tuple, x, y, z
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """World-frame displacement samples from ``R p0 + t`` with the transform samples, into
    ws.wx, ws.wy, ws.wz. ``cal = (R_m - R, t_m - t, R_m)`` in the working dtype."""
    dR, dtr, Rs = cal
    p0 = ch.p0
    # R_m (p0 + d) + t_m - (R p0 + t) = (R_m - R) p0 + (t_m - t) + R_m d
    a = ws.a
    for i, w in enumerate((ws.wx, ws.wy, ws.wz)):
        np.multiply(dR[:, i, 0], p0[:, 0:1], out=w)
        w += np.multiply(dR[:, i, 1], p0[:, 1:2], out=a)
        w += np.multiply(dR[:, i, 2], p0[:, 2:3], out=a)
        w += dtr[:, i]
        w += np.multiply(Rs[:, i, 0], x, out=a)
        w += np.multiply(Rs[:, i, 1], y, out=a)
        w += np.multiply(Rs[:, i, 2], z, out=a)
    return ws.wx, ws.wy, ws.wz


def _sample_chunk(
    ws: _Workspace, ch: _Chunk, rng: np.random.Generator, cal: tuple | None,
    n_gr: float, n_ref: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, dict[str, np.ndarray]]:
    """Draws of one chunk: the total's displacement samples ``x, y, z`` ((n, M) views of the
    workspace: from ``R p0 + t`` in the world frame when ``cal`` is given, else from ``p0`` in
    the station frame) and the per-source covariances (station frame)."""
    draws = _draw_errors(ws, ch, rng, n_gr, n_ref)
    by_source = _single_source_covariances(ws, ch, draws)
    x, y, z = _total_displacements(ws, ch, draws)
    if cal is not None:
        x, y, z = _to_world_samples(ws, ch, cal, x, y, z)
    return x, y, z, by_source


def _rotate(R: np.ndarray, cov: np.ndarray) -> np.ndarray:
    return np.einsum("ij,njk,lk->nil", R, cov, R, optimize=True)


def _checked_arguments(samples, rng, chunk_size, workers, dtype) -> tuple[int, int, int, type]:
    """``(M, chunk_size, workers, dtype)`` of :func:`mc_covariances`, checked and defaulted.

    Raises
    ------
    InputError
        On fewer than 2 samples, an ``rng`` that is no Generator, a chunk size below 1, or a
        dtype other than float64 / float32.
    """
    M = int(samples)
    if M < 2:
        raise InputError(f"Expected samples >= 2 for the Monte Carlo engine, got {samples!r}")
    if not isinstance(rng, np.random.Generator):
        raise InputError(
            "The Monte Carlo engine needs rng = numpy.random.Generator "
            f"(e.g. np.random.default_rng(seed)), got {type(rng).__name__}"
        )
    if chunk_size is None:
        chunk_size = max(1, CHUNK_ELEMENTS // M)
    chunk_size = int(chunk_size)
    if chunk_size < 1:
        raise InputError(f"Expected chunk_size >= 1, got {chunk_size}")
    workers = max(1, int(workers))
    dtype = np.dtype(dtype).type
    if dtype not in (np.float64, np.float32):
        raise InputError(f"Expected dtype float64 or float32, got {dtype}")
    return M, chunk_size, workers, dtype


class _ChunkPlan(NamedTuple):
    """How the N measurements are cut into chunks and spread over the threads (internal)."""

    N: int
    chunk_size: int
    starts: list[int]  # first measurement of each chunk
    seeds: np.ndarray  # (n_chunks, 2) int64: the seed of each chunk's child generator
    bitgen: type  # the bit generator of the rng passed in (the children use the same kind)
    groups: list[range]  # the chunks of each thread (contiguous)

    def chunk(self, k: int) -> slice:
        """The measurements of chunk ``k``."""
        return slice(self.starts[k], min(self.starts[k] + self.chunk_size, self.N))

    def generator(self, k: int) -> np.random.Generator:
        """The child generator of chunk ``k`` (independent of the thread that runs it)."""
        seq = np.random.SeedSequence([int(s) for s in self.seeds[k]])
        return np.random.Generator(self.bitgen(seq))


def _plan_chunks(N: int, chunk_size: int, workers: int, rng: np.random.Generator) -> _ChunkPlan:
    """Chunks of ``chunk_size`` measurements, one seed each drawn from ``rng``, and contiguous
    groups of chunks per thread; each chunk has its own generator, so the result does not
    depend on the number of threads."""
    starts = list(range(0, N, chunk_size))
    seeds = rng.integers(0, 2**63 - 1, size=(len(starts), 2), dtype=np.int64)
    workers = min(workers, len(starts))
    bounds = np.linspace(0, len(starts), workers + 1).astype(int)
    groups = [range(bounds[i], bounds[i + 1]) for i in range(workers)]
    return _ChunkPlan(N, chunk_size, starts, seeds, type(rng.bit_generator), groups)


def _run_chunks(
    nom: Nominal, model: NoiseModel, plan: _ChunkPlan, cal_work: tuple | None,
    atmosphere: tuple[float, float], M: int, dtype,
) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """Run every chunk of ``plan`` (one thread per group, each with its own workspace):
    total and per-source covariances, in the frames :func:`_run_chunk` returns.
    ``atmosphere`` is ``(N_gr, N_REF)`` of :func:`_atmosphere_constants`."""
    N = plan.N
    n_gr, n_ref = atmosphere
    total = np.empty((N, 3, 3))
    by_source = {s: np.zeros((N, 3, 3)) for s in model.sources}

    def work(ks: range) -> None:
        ws = _Workspace(min(plan.chunk_size, N), M, dtype)
        for k in ks:
            sl = plan.chunk(k)
            ws.rows(sl.stop - sl.start)
            tot, bys = _run_chunk(ws, _Chunk(nom, model, sl, dtype), plan.generator(k),
                                  cal_work, n_gr, n_ref)
            total[sl] = tot
            for s, c in bys.items():
                by_source[s][sl] = c

    if len(plan.groups) == 1:
        work(plan.groups[0])
    else:
        with ThreadPoolExecutor(max_workers=len(plan.groups)) as ex:
            list(ex.map(work, plan.groups))
    return total, by_source


def _to_world(
    nom: Nominal, model: NoiseModel, cal: tuple | None, total: np.ndarray,
    by_source: dict[str, np.ndarray],
) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """Rotate the station-frame covariances into the world frame (the total only when it was
    not sampled in the world frame) and add the calibration source's covariance."""
    R = nom.R
    srcs = model.sources
    for s in srcs:
        if s != "calibration":
            by_source[s] = _rotate(R, by_source[s])
    if cal is None:
        total = _rotate(R, total)
    if "calibration" in srcs:
        if cal is None:
            by_source["calibration"] = np.zeros((nom.d.shape[0], 3, 3))
        else:
            by_source["calibration"] = calibration_covariance_from_samples(
                nom.xyz_station, cal[0], cal[1]
            )
    return total, by_source


def mc_covariances(
    nom: Nominal,
    model: NoiseModel,
    T_world_station=None,
    *,
    samples: int = 1000,
    rng: np.random.Generator,
    chunk_size: int | None = None,
    workers: int = 1,
    dtype=np.float64,
) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """World-frame covariances (N, 3, 3) by Monte Carlo: the total and, per source of
    ``model.sources``, that source alone (docs/noise-model.md#monte-carlo).

    ``nom``: :func:`rtsgt.noise.model.prepare_nominal`'s; ``T_world_station``: the calibration
    samples (:func:`transform_samples`); M = ``samples`` >= 2 draws of ``rng`` per
    measurement, ``chunk_size`` measurements per chunk (default ``CHUNK_ELEMENTS // M``) on
    ``workers`` threads (the result does not depend on it); ``dtype`` float64 or float32: the
    working precision of the sampled displacements (results in float64).
    """
    M, chunk_size, workers, dtype = _checked_arguments(samples, rng, chunk_size, workers, dtype)
    # the total is sampled in the world frame with the transform samples (R_m, t_m) when the
    # calibration source is on, and rotated by the mean rotation otherwise
    cal = transform_samples(T_world_station, M, rng) if "calibration" in model.sources else None
    cal_work = None
    if cal is not None:
        cal_work = (
            (cal[0] - nom.R).astype(dtype), (cal[1] - nom.t_ws).astype(dtype),
            cal[0].astype(dtype),
        )
    atmosphere = _atmosphere_constants(model)
    plan = _plan_chunks(nom.d.shape[0], chunk_size, workers, rng)
    total, by_source = _run_chunks(nom, model, plan, cal_work, atmosphere, M, dtype)
    return _to_world(nom, model, cal, total, by_source)
