"""Extrinsic calibration of the stations from ground control points (GCPs).

Owns the rigid fit of every station's markers onto the reference station's (6 or 4 DOF,
unweighted, trace- or GLS-weighted), its Monte Carlo covariance (the paper's, section III-E),
the fit and levelling checks and the shots' variance components, and the GCPs' atmospheric
correction and world positions. Model, weights, checks and measured numbers:
docs/noise-model.md#extrinsic-calibration; the shots and their covariance:
:mod:`rtsgt.calibration.shots`; the records: :mod:`rtsgt.calibration.result`.
"""

from __future__ import annotations

import warnings
from dataclasses import replace

import numpy as np

from rtsgt.calibration.result import CalibrationResult, FitCheck, LevellingCheck
from rtsgt.calibration.shots import (
    ShotSetup,
    check_args,
    curvature_tilt,
    marker_residuals,
    natural_key,
    polar_point_covariance,
    setup_shots,
    with_extra_variance,
)
from rtsgt.choices import DEFAULT_WEIGHTING
from rtsgt.errors import GeometryError, RtsgtWarning
from rtsgt.geometry.kabsch import kabsch, kabsch_yaw
from rtsgt.geometry.so3 import exp_so3, hat
from rtsgt.geometry.transform import RigidTransform, perturbation
from rtsgt.measurement.atmosphere import instrument_correction_ppm
from rtsgt.measurement.instruments import TRIMBLE_S7, InstrumentProfile
from rtsgt.measurement.polar import polar_to_cartesian
from rtsgt.noise.model import NoiseModel
from rtsgt.noise.perturb import sample_polar_errors
from rtsgt.pose.reference import block_diagonal
from rtsgt.pose.weighted import gls_weights, refine_batches
from rtsgt.stats import ratio_interval
from rtsgt.types import GcpShots, WeatherSeries

__all__ = ["calibrate", "extra_shot_variance", "fit_stations", "gcp_atmospheric_correction",
           "gcp_world_positions"]


def _weights(setup: ShotSetup, idx_s, idx_r, instrument) -> np.ndarray:
    """``w_i = 1 / (tr C_ref,i + tr C_s,i)`` (1/m^2), docs/noise-model.md#weights-of-the-gcps."""
    C = polar_point_covariance(setup.hz, setup.v, setup.d, instrument)
    tr = np.trace(C, axis1=-2, axis2=-1)
    return 1.0 / (tr[idx_s] + tr[idx_r])


def _fit_4dof(p: np.ndarray, q: np.ndarray, w, tilt: np.ndarray | None = None, *,
              check: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """``q ~ exp([omega + tilt]x) R_z(psi) p + t`` with ``omega`` the curvature tilt of ``t``
    (docs/noise-model.md#levelled-stations-4-dof); batched over leading axes of ``p``, ``q``, ``tilt``."""
    t = kabsch_yaw(p, q, w, check=check)[1]
    return _levelled(t, tilt, lambda T, _: kabsch_yaw(p, q @ T, w, check=check))


def _levelled(t: np.ndarray, tilt: np.ndarray | None, fit_tilted) -> tuple[np.ndarray, np.ndarray]:
    """The 4-DOF transform from the fit of the yaw and translation in the frame turned by the
    curvature tilt of ``t`` (plus the compensators' ``tilt``), twice (docs/noise-model.md#levelled-stations-4-dof): ``fit_tilted(T, t)`` returns ``R_z`` and ``t'`` of ``T^T q ~ R_z p + t'`` (rows
    ``q T = (T^T q)^T``); then ``R = T R_z``, ``t = T t'``."""
    for _ in range(2):
        omega = curvature_tilt(t)
        if tilt is not None:
            omega = omega + tilt
        T = exp_so3(omega)
        Rz, t_tilted = fit_tilted(T, t)
        t = np.einsum("...ij,...j->...i", T, t_tilted)
    return T @ Rz, t


def _fit(setup: ShotSetup, s: str, p: np.ndarray, q: np.ndarray, w, model: str,
         tilt: np.ndarray | None = None, check: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """The fit of station ``s``'s points ``p`` onto the reference's ``q`` under ``model``."""
    try:
        if model == "4dof":
            return _fit_4dof(p, q, w, tilt, check=check)
        return kabsch(p, q, w, check=check)
    except GeometryError as exc:
        raise GeometryError(f"station {s} (markers {', '.join(setup.pairs[s][2])}): {exc}"
                            ) from None


def _nominal(setup: ShotSetup, weighting: str, instrument, model: str) -> dict[str, tuple]:
    """Closed-form fit of each non-reference station: ``{s: (R, t, weights or None)}``; trace
    weights for ``"gls"`` too (its start and the rotation its weights are evaluated at)."""
    out = {}
    for s, (idx_s, idx_r, _) in setup.pairs.items():
        w = _weights(setup, idx_s, idx_r, instrument) if weighting != "none" else None
        R, t = _fit(setup, s, setup.points[idx_s], setup.points[idx_r], w, model)
        out[s] = (R, t, w)
    return out


def _gls_station_weights(setup: ShotSetup, s: str, R: np.ndarray, C: np.ndarray) -> np.ndarray:
    """``W = C^-1`` of station ``s``'s stacked residuals, ``C_i = C_ref,i + R C_s,i R^T``
    (docs/noise-model.md#weights-of-the-gcps), (3K, 3K)."""
    idx_s, idx_r, _ = setup.pairs[s]
    return gls_weights(block_diagonal(C[idx_r]), block_diagonal(C[idx_s]), R)


def _gls_yaw(p: np.ndarray, y: np.ndarray, W: np.ndarray, psi: np.ndarray, t: np.ndarray,
             steps: int = 4) -> tuple[np.ndarray, np.ndarray]:
    """Gauss-Newton of ``min e^T W e``, ``e = y - (R_z(psi) p + t)`` stacked, over the yaw and
    the translation; ``p, y`` (S, K, 3), ``W`` (3K, 3K), the start ``psi`` (S,), ``t``
    (S, 3). The problem is linear in ``t`` and nearly so in ``psi`` (a start within
    milliradians): the steps fall quadratically, to round-off in three or four."""
    S, K, _ = p.shape
    psi, t = psi.astype(float).copy(), t.astype(float).copy()
    J = np.zeros((S, K, 3, 4))
    J[..., 1:] = np.eye(3)
    for _ in range(steps):
        c, sn = np.cos(psi)[:, None], np.sin(psi)[:, None]
        a = np.stack([c * p[..., 0] - sn * p[..., 1], sn * p[..., 0] + c * p[..., 1],
                      p[..., 2]], axis=-1)
        e = (y - a - t[:, None, :]).reshape(S, 3 * K)
        J[..., 0, 0], J[..., 1, 0] = -a[..., 1], a[..., 0]  # d(R_z p)/dpsi = e_z x R_z p
        Jf = J.reshape(S, 3 * K, 4)
        JW = np.swapaxes(Jf, 1, 2) @ W
        step = np.linalg.solve(JW @ Jf, (JW @ e[..., None]))[..., 0]
        psi += step[:, 0]
        t += step[:, 1:]
    return psi, t


def _gls_fit(p: np.ndarray, q: np.ndarray, W: np.ndarray, R0: np.ndarray, t0: np.ndarray,
             model: str, tilt: np.ndarray | None = None
             ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The generalised least-squares fit of station points ``p`` onto the reference's ``q``
    (S, K, 3) with the weights ``W`` (3K, 3K), from the start ``R0, t0`` (a station's nominal
    fit), under ``model`` (the 4-DOF one with the compensators' ``tilt`` (S, 3), as
    :func:`_fit_4dof`). Returns ``R`` (S, 3, 3), ``t`` (S, 3) and whether each converged (S,)
    (else its last iterate: shots far from any rigid fit, e.g. a mirrored station)."""
    S = q.shape[0]
    if model == "6dof":
        R, t, conv, _ = refine_batches(p[None], q[None], W[None], R0[None, None],
                                       t0[None, None])
        return R[0], t[0], conv[0]
    # 4 DOF: R = exp([omega + tilt]x) R_z(psi); the weights, evaluated at the nominal rotation,
    # are held as they are in the tilted frame (the tilt is microradians)
    psi = np.full(S, np.arctan2(R0[1, 0], R0[0, 0]))

    def yaw_fit(T, t):
        nonlocal psi  # each pass starts from the last one's yaw
        psi, t_tilted = _gls_yaw(p, q @ T, W, psi, np.einsum("sji,sj->si", T, t))
        return exp_so3(psi[:, None] * np.array([0.0, 0.0, 1.0])), t_tilted

    R, t = _levelled(np.broadcast_to(t0, (S, 3)), tilt, yaw_fit)
    return R, t, np.ones(S, dtype=bool)


def fit_stations(
    shots: GcpShots,
    *,
    reference_station: str = "1",
    weighting: str = DEFAULT_WEIGHTING,
    instrument: InstrumentProfile = TRIMBLE_S7,
    model: str = "6dof",
) -> dict[str, RigidTransform]:
    """``T_world_station`` of every station (the reference: identity), fitted by marker onto
    the reference station's shots, without covariance (:func:`calibrate` adds it).

    Shots with a non-zero status are left out; ``weighting`` "gls", "trace" or "none"
    (docs/noise-model.md#weights-of-the-gcps) under the ``instrument`` model; ``model`` "6dof"
    or "4dof" (docs/noise-model.md#levelled-stations-4-dof). Raises :class:`InputError` for an
    unknown reference, a single station or a marker shot twice by one station, and
    :class:`GeometryError` for fewer than 3 valid shared markers or (nearly) collinear ones.
    """
    check_args(instrument, weighting, model)
    ref = str(reference_station)
    setup = setup_shots(shots, ref, instrument)
    R, t, _, _ = _fits(setup, ref, weighting, instrument, model,
                    polar_point_covariance(setup.hz, setup.v, setup.d, instrument), False)
    out = {ref: RigidTransform(np.eye(3), np.zeros(3), np.zeros((6, 6)), "world", f"station_{ref}")}
    for s in setup.stations:
        if s != ref:
            out[s] = RigidTransform(R[s], t[s], None, "world", f"station_{s}")
    return out


def _fits(setup: ShotSetup, ref: str, weighting: str, instrument, model: str, C: np.ndarray,
          variance_components: bool) -> tuple[dict, dict, dict, np.ndarray]:
    """The nominal fit of every station (the reference ``ref``'s identity included): ``R, t``
    and the fit's weights by station (trace weights (K,), ``W`` (3K, 3K) under ``"gls"``, or
    None), and the variance components (:func:`extra_shot_variance`, from the generalised
    least-squares residuals, which do not depend on the fit they start from) when
    ``variance_components``, else zeros; under ``"gls"`` they enter the weights."""
    R, t, w = {ref: np.eye(3)}, {ref: np.zeros(3)}, {}
    for s, (Rs, ts, ws) in _nominal(setup, weighting, instrument, model).items():
        R[s], t[s], w[s] = Rs, ts, ws
    extra = extra_shot_variance(setup, R, t, C, model) if variance_components else np.zeros(2)
    if weighting == "gls":
        Cx = with_extra_variance(C, extra)
        for s, (idx_s, idx_r, _) in setup.pairs.items():
            w[s] = _gls_station_weights(setup, s, R[s], Cx)
            Rs, ts, ok = _gls_fit(setup.points[idx_s][None], setup.points[idx_r][None], w[s],
                                  R[s], t[s], model)
            if ok[0]:
                R[s], t[s] = Rs[0], ts[0]
            else:
                warnings.warn(f"station {s}: the generalised least-squares fit of the GCPs did "
                              "not converge (shots far from any rigid fit: check the "
                              "residuals); the trace-weighted fit stands", RtsgtWarning,
                              stacklevel=3)
    return R, t, w, extra


def _gls_step(setup: ShotSetup, R: dict, t: dict, C: np.ndarray, s: str, model: str = "6dof"):
    """One Gauss-Newton step of station ``s``'s generalised least-squares fit from the fit
    ``R, t`` (in the left perturbation: ``R p ~ R p - [R p]x dphi``, ``t ~ t + dt``; under
    ``"4dof"`` ``dphi`` along the station's vertical only), from the shots' covariance ``C``.

    Returns the residuals after the step, their covariance ``C_ref,i + R C_s,i R^T``, the step
    ``(dphi, dt)`` (``(dpsi, dt)`` under ``"4dof"``) and the normal matrix ``J^T C^-1 J``, whose
    inverse is the covariance of the fitted parameters."""
    idx_s, idx_r, _ = setup.pairs[s]
    Ci = C[idx_r] + R[s] @ C[idx_s] @ R[s].T
    W = np.linalg.inv(Ci)
    Rp = setup.points[idx_s] @ R[s].T
    r = setup.points[idx_r] - Rp - t[s]
    rot = hat(Rp) if model == "6dof" else hat(Rp) @ R[s][:, 2:3]
    J = np.concatenate([rot, np.broadcast_to(-np.eye(3), Rp.shape + (3,))], axis=2)
    JW = np.swapaxes(J, 1, 2) @ W
    N = np.sum(JW @ J, axis=0)
    step = np.linalg.lstsq(N, -np.sum(JW @ r[..., None], axis=0), rcond=None)[0]
    return r + (J @ step)[..., 0], Ci, step[:, 0], N


def _gls_residuals(setup: ShotSetup, R: dict, t: dict, C: np.ndarray,
                   s: str, model: str = "6dof") -> tuple[np.ndarray, np.ndarray]:
    """Residuals of station ``s``'s generalised least-squares fit and their covariance
    (:func:`_gls_step`)."""
    r, Ci, _, _ = _gls_step(setup, R, t, C, s, model)
    return r, Ci


def _levelling_checks(setup: ShotSetup, R: dict, t: dict, C: np.ndarray,
                      sigma_tilt: float) -> dict[str, LevellingCheck]:
    """:class:`LevellingCheck` of every fitted station: one 6-DOF Gauss-Newton step from the
    fit ``R, t`` with the curvature's tilt (a 4-DOF fit, or a 6-DOF one turned to it)."""
    out = {}
    for s in setup.pairs:
        yaw = np.arctan2(R[s][1, 0] - R[s][0, 1], R[s][0, 0] + R[s][1, 1])
        Rl = {s: exp_so3(curvature_tilt(t[s])) @ exp_so3(np.array([0.0, 0.0, yaw]))}
        _, _, step, N = _gls_step(setup, Rl, t, C, s)
        cov = np.linalg.inv(N)[:2, :2] + 2.0 * sigma_tilt**2 * np.eye(2)
        tilt = step[:2]
        chi2 = float(tilt @ np.linalg.solve(cov, tilt))
        out[s] = LevellingCheck(tilt, np.sqrt(np.diag(cov)), chi2, float(np.exp(-0.5 * chi2)))
    return out


def _axis_dof(markers: int, model: str) -> np.ndarray:
    """Degrees of freedom per world axis of a fit of ``markers`` markers: the 6 parameters
    shared evenly among the axes, or the 4 of ``"4dof"`` (x, y and the yaw on the
    horizontal axes, z on the vertical)."""
    return markers - (np.full(3, 2.0) if model == "6dof" else np.array([1.5, 1.5, 1.0]))


def _fit_checks(setup: ShotSetup, R: dict, t: dict, C: np.ndarray,
                model: str = "6dof") -> dict[str, FitCheck]:
    """:class:`FitCheck` of every fitted station (docs/self-checks.md#gcp-fit), shots' covariance ``C``."""
    out = {}
    for s, (_, _, markers) in setup.pairs.items():
        r, Ci = _gls_residuals(setup, R, t, C, s, model)
        K = len(markers)
        dof = 3 * K - (6 if model == "6dof" else 4)
        chi2 = float(np.einsum("ki,kij,kj->", r, np.linalg.inv(Ci), r))
        axes = np.sum(r ** 2 / np.diagonal(Ci, axis1=-2, axis2=-1), axis=0)
        if dof > 0:
            out[s] = FitCheck(K, dof, chi2 / dof, axes / _axis_dof(K, model),
                              ratio_interval(dof))
        else:
            out[s] = FitCheck(K, dof, float("nan"), np.full(3, np.nan), (np.nan, np.nan))
    return out


def extra_shot_variance(setup: ShotSetup, R: dict, t: dict, C: np.ndarray,
                        model: str = "6dof") -> np.ndarray:
    """Variance components (m^2) to add to every shot, horizontal and vertical, so that the
    pooled per-axis variance factors of the fits are 1 (docs/self-checks.md#variance-components-the-model-changed-where-the-check-fails); 0 for a group whose factor is inside its 95 % interval."""
    extra = np.zeros(2)
    checks = [(0, [0, 1]), (1, [2])]
    dof = sum(_axis_dof(len(m), model) for (_, _, m) in setup.pairs.values())
    if np.any(dof <= 0):
        return extra

    def factor(group: int, x: float) -> float:
        e = extra.copy()
        e[group] = x
        Cx = with_extra_variance(C, e)
        total = 0.0
        for s in setup.pairs:
            r, Ci = _gls_residuals(setup, R, t, Cx, s, model)
            total += float(np.sum(r[:, axes] ** 2 / np.diagonal(Ci, axis1=-2, axis2=-1)[:, axes]))
        return total / float(dof[axes].sum())

    for _ in range(3):  # the two groups interact a little through the fit: alternate
        for group, axes in checks:
            if factor(group, 0.0) <= ratio_interval(float(dof[axes].sum()))[1]:
                extra[group] = 0.0
                continue
            hi = 1e-8
            while factor(group, hi) > 1.0 and hi < 1.0:
                hi *= 4.0
            lo = 0.0
            for _ in range(50):  # bisection on the variance, to 1e-15 relative
                mid = 0.5 * (lo + hi)
                lo, hi = (mid, hi) if factor(group, mid) > 1.0 else (lo, mid)
            extra[group] = hi
    return extra


def _perturbed_shots(setup: ShotSetup, instrument: InstrumentProfile, extra: np.ndarray,
                     model: str, ref: str, M: int, rng: np.random.Generator):
    """M Monte Carlo draws of every valid shot, (M, N, 3) station frames (the variance
    components ``extra`` added), and under ``"4dof"`` each station's compensator error
    against the reference's, ``{station: (M, 3)}`` (else None)."""
    hz_m, v_m, d_m = sample_polar_errors(setup.hz, setup.v, setup.d, instrument, M, rng)
    points_m = polar_to_cartesian(hz_m, v_m, d_m)
    if extra.any():  # the variance components, in each station's (levelled) frame
        points_m += rng.standard_normal(points_m.shape) * np.sqrt(extra[[0, 0, 1]])
    if model != "4dof":
        return points_m, None
    comp = rng.standard_normal((M, len(setup.stations), 2)) * instrument.sigma_tilt
    comp = np.concatenate([comp, np.zeros((M, len(setup.stations), 1))], axis=2)
    return points_m, {st: comp[:, k] - comp[:, setup.stations.index(ref)]
                      for k, st in enumerate(setup.stations)}


def _station_samples(setup: ShotSetup, s: str, points_m: np.ndarray, tilt: np.ndarray | None,
                     R: np.ndarray, t: np.ndarray, weights, weighting: str, model: str):
    """Station ``s`` refitted to every draw ``points_m`` (M, N, 3) from its fit ``R, t``:
    the 6x6 covariance of the left perturbations and the samples ``Rm`` (M, 3, 3),
    ``tm`` (M, 3)."""
    idx_s, idx_r, _ = setup.pairs[s]
    if weighting == "gls":
        Rm, tm, ok = _gls_fit(points_m[:, idx_s], points_m[:, idx_r], weights, R, t, model, tilt)
        if not ok.all():
            warnings.warn(f"station {s}: the generalised least-squares fit did not "
                          f"converge for {int((~ok).sum())} of {ok.size} Monte Carlo "
                          "samples (shots far from any rigid fit: check the "
                          "residuals); their last iterates are kept", RtsgtWarning,
                          stacklevel=3)
    else:
        Rm, tm = _fit(setup, s, points_m[:, idx_s], points_m[:, idx_r], weights, model, tilt,
                      check=False)
    cov = np.cov(perturbation(R, t, Rm, tm), rowvar=False)  # (x, y, z, rx, ry, rz)
    return 0.5 * (cov + cov.T), Rm, tm


def calibrate(
    shots: GcpShots,
    *,
    reference_station: str = "1",
    instrument: InstrumentProfile = TRIMBLE_S7,
    samples: int = 1000,
    rng: np.random.Generator | None = None,
    weighting: str = DEFAULT_WEIGHTING,
    variance_components: bool = True,
    model: str = "6dof",
) -> CalibrationResult:
    """Calibrate all stations from GCP shots, with a Monte Carlo 6x6 covariance per station.

    ``reference_station``: the world frame; ``instrument``: the shots' and compensators'
    noise; ``samples``: M Monte Carlo draws of ``rng`` (0: the fit alone); ``weighting``
    "gls", "trace" or "none" (docs/noise-model.md#weights-of-the-gcps);
    ``variance_components``: add the variance the residuals show beyond the instrument model
    (docs/self-checks.md#variance-components-the-model-changed-where-the-check-fails; False:
    the paper's); ``model`` "6dof" (the paper) or "4dof"
    (docs/noise-model.md#levelled-stations-4-dof). Raises as :func:`fit_stations`.
    """
    check_args(instrument, weighting, model)
    if isinstance(samples, bool) or not isinstance(samples, (int, np.integer)):
        raise TypeError(f"Expected an integer number of samples, got {samples!r}")
    if samples < 0 or samples == 1:
        raise ValueError(f"Expected samples = 0 or >= 2, got {samples}")
    rng = np.random.default_rng() if rng is None else rng
    ref = str(reference_station)
    setup = setup_shots(shots, ref, instrument)
    C = polar_point_covariance(setup.hz, setup.v, setup.d, instrument)
    R, t, weights, extra = _fits(setup, ref, weighting, instrument, model, C,
                                 variance_components)
    M = int(samples)
    if M:
        points_m, tilt_of = _perturbed_shots(setup, instrument, extra, model, ref, M, rng)
    transforms = {}
    for s in setup.stations:
        if s == ref:
            cov = np.zeros((6, 6))
            Rm = np.broadcast_to(np.eye(3), (M, 3, 3)).copy() if M else None
            tm = np.zeros((M, 3)) if M else None
        elif M:
            cov, Rm, tm = _station_samples(setup, s, points_m, None if tilt_of is None
                                           else tilt_of[s], R[s], t[s], weights[s], weighting,
                                           model)
        else:
            cov = Rm = tm = None
        transforms[s] = RigidTransform(R[s], t[s], cov, "world", f"station_{s}", Rm, tm)
    used = {s: setup.pairs[s][2] for s in setup.pairs}
    used[ref] = tuple(sorted(setup.used_markers, key=natural_key))
    return CalibrationResult(
        reference_station=ref, transforms=transforms, residuals=marker_residuals(setup, R, t),
        markers_used={s: used[s] for s in setup.stations}, markers_skipped=setup.skipped,
        excluded_shots=setup.excluded, samples=M, weighting=weighting,
        fit_checks=_fit_checks(setup, R, t, C, model),
        extra_shot_sigma_m=(float(np.sqrt(extra[0])), float(np.sqrt(extra[1]))), model=model,
        levelling=_levelling_checks(setup, R, t, with_extra_variance(C, extra),
                                    instrument.sigma_tilt))


def gcp_atmospheric_correction(
    gcp: GcpShots, model: NoiseModel, weather: WeatherSeries | None, fallback_t: float
) -> GcpShots:
    """``gcp`` with the first-velocity correction of ``model``'s instrument applied to its
    distances, each at the ``weather`` of its time, or of ``fallback_t`` (s, the start of
    tracking) outside the weather series (docs/noise-model.md#extrinsic-calibration);
    unchanged without weather."""
    if weather is None:
        return gcp
    n = len(gcp.d)
    t = np.full(n, float(fallback_t)) if gcp.t is None else np.asarray(gcp.t, dtype=float)
    inside = np.isfinite(t) & (t >= weather.t[0]) & (t <= weather.t[-1])
    t = np.where(inside, t, float(fallback_t))
    temp, pres, hum = weather.at(t)
    ppm = np.asarray(instrument_correction_ppm(model.instrument, temp, pres, hum,
                                               model.vapour_formula), dtype=float)
    c = float(gcp.additive_constant)
    d = (np.asarray(gcp.d, dtype=float) + c) * (1.0 + 1e-6 * ppm) - c
    return replace(gcp, d=d)


def gcp_world_positions(
    gcp: GcpShots | None, transforms: dict[str, RigidTransform]
) -> tuple[np.ndarray | None, tuple[str, ...]]:
    """World position (G, 3), m, of every marker shot validly by a station of ``transforms``,
    the mean over its shots, and the marker names in natural order (``"2"`` before ``"10"``);
    ``(None, ())`` without GCPs."""
    if gcp is None or len(gcp) == 0:
        return None, ()
    ok = (np.asarray(gcp.status) == 0) & np.isin(gcp.station, list(transforms))
    if not ok.any():
        return None, ()
    p_station = polar_to_cartesian(gcp.hz[ok], gcp.v[ok], gcp.distance[ok])
    p_world = np.empty_like(p_station)
    stations = gcp.station[ok]
    for s in np.unique(stations):  # one transform per station (a handful)
        m = stations == s
        p_world[m] = transforms[str(s)].apply(p_station[m])
    markers = gcp.marker[ok]
    names = tuple(sorted(set(markers.tolist()), key=lambda x: (len(x), x)))
    xyz = np.array([p_world[markers == k].mean(axis=0) for k in names])
    return xyz, names
