"""The per-prism GPs of a run: fitted to each prism track, queried together at the pose times.

How the noise sources enter the GP: it treats measurement noise as independent from one
measurement to the next, which is true of the white sources (instrument, tilt) only; the
systematic ones (atmosphere, time synchronisation, calibration) are added to the interpolated
position afterwards, at their full value (docs/interpolation.md). Qc is chosen by
leave-one-out cross-validation per axis by default (:mod:`rtsgt.interpolation.loo`), then
scaled per class of the robot's motion where that predicts held-out measurements better
(:mod:`rtsgt.interpolation.motion`). The motion prior (white noise on the acceleration or on
the jerk, :mod:`rtsgt.interpolation.gp`) is the option's, or with ``prior = "select"`` per
track the one whose held-out windows of 1-2 s are predicted better
(:func:`rtsgt.interpolation.windows.window_score`).
"""

from __future__ import annotations

import warnings
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np

from rtsgt.errors import InputError, RtsgtWarning
from rtsgt.interpolation.gp import GPTrack, fit_track
from rtsgt.interpolation.loo import fit_qc_loo
from rtsgt.interpolation.motion import fit_motion_prior, motion_events
from rtsgt.interpolation.options import InterpolationOptions
from rtsgt.interpolation.windows import window_score
from rtsgt.noise.coupling import StationCoupling, joint_prism_covariance
from rtsgt.noise.sources import (
    CORRELATED_NOISE_SOURCE,
    SYSTEMATIC_NOISE_SOURCES,
    WHITE_NOISE_SOURCES,
)
from rtsgt.parallel import available_cores
from rtsgt.types import PrismTrack

__all__ = ["PrismsAtTimes", "choose_prior", "fit_gps", "fit_prism_gp", "query_prisms", "query_grid",
           "gp_covariance",
           "gp_velocities",
           "WHITE_SOURCES", "SYSTEMATIC_SOURCES"]

#: Noise sources whose errors are taken as independent between measurements (fed to the GP):
#: the white ones and, where their noise is correlated in time, what its inflation adds
#: (:mod:`rtsgt.noise.correlated`).
WHITE_SOURCES = (*WHITE_NOISE_SOURCES, CORRELATED_NOISE_SOURCE)
#: Noise sources whose errors are shared by many measurements (added after the GP).
SYSTEMATIC_SOURCES = SYSTEMATIC_NOISE_SOURCES


@dataclass(frozen=True)
class PrismsAtTimes:
    """The interpolated prisms at the query times.

    Attributes
    ----------
    t : ndarray, shape (T,)
    xyz : ndarray, shape (T, n, 3)
        World positions, m.
    cov : ndarray, shape (T, n, 3, 3)
        Total covariance (GP posterior plus systematic sources), m^2.
    cov_gp : ndarray, shape (T, n, 3, 3)
        GP posterior covariance alone.
    cov_by_source : dict str -> ndarray (T, n, 3, 3)
        Each source's covariance, interpolated from the measurements.
    nearest_dt : ndarray, shape (T, n)
        Time to the nearest measurement of each prism, s.
    cov_joint : ndarray, shape (T, 3n, 3n), optional
        Joint covariance of the stacked prisms: the blocks of ``cov`` on the diagonal, and off
        it the calibration errors two stations share (:class:`StationCoupling`).
    """

    t: np.ndarray
    xyz: np.ndarray
    cov: np.ndarray
    cov_gp: np.ndarray
    cov_by_source: dict[str, np.ndarray]
    nearest_dt: np.ndarray
    cov_joint: np.ndarray | None = None

    @property
    def pose_covariance(self) -> np.ndarray:
        """What the pose engines take: the joint (T, 3n, 3n) covariance when the prisms share
        errors (the station calibrations), else the per-prism blocks (T, n, 3, 3)."""
        return self.cov if self.cov_joint is None else self.cov_joint


def _interp_cov(track: PrismTrack, sources: tuple[str, ...], t: np.ndarray) -> dict[str, np.ndarray]:
    """Per-source covariance at times ``t``, linear between neighbouring measurements."""
    out = {}
    for s in sources:
        c = track.cov_by_source.get(s)
        if c is None:
            continue
        flat = c.reshape(len(track), 9)
        vals = np.stack([np.interp(t, track.t, flat[:, j]) for j in range(9)], axis=-1)
        out[s] = vals.reshape(t.shape + (3, 3))
    return out


def gp_covariance(track: PrismTrack, gp_noise: str) -> np.ndarray:
    """Measurement covariance given to the GP: the white sources only, or the total."""
    if gp_noise == "all" or not track.cov_by_source:
        return track.cov
    white = [track.cov_by_source[s] for s in WHITE_SOURCES if s in track.cov_by_source]
    if not white:
        raise InputError("No white noise source (instrument or tilt) to weight the GP with")
    return np.sum(white, axis=0)


def query_grid(intervals: np.ndarray, rate_hz: float) -> np.ndarray:
    """Regular query times at ``rate_hz`` inside each interval (aligned to whole periods)."""
    step = 1.0 / rate_hz
    parts = []
    for a, b in np.asarray(intervals, dtype=float).reshape(-1, 2):
        k0, k1 = np.ceil(a / step - 1e-9), np.floor(b / step + 1e-9)
        if k1 >= k0:
            parts.append(np.arange(k0, k1 + 1) * step)
    return np.concatenate(parts) if parts else np.empty(0)


def fit_prism_gp(data, qc: float | str, max_gap_s: float, name: str,
                 prior: str = "wnoa") -> tuple[GPTrack, dict]:
    """Fit one prism's GP with rtsgt's Qc policy (the one every command uses).

    Parameters
    ----------
    data : PrismTrack or tuple (t, xyz, cov)
        The measurements and the covariance the GP is given.
    qc : {"loo", "likelihood"} or float
        ``"loo"`` (the default of :class:`rtsgt.options.InterpolationOptions`): leave-one-out
        cross-validation of a diagonal Qc (one PSD per world axis), which calibrates the GP for
        interpolation (:mod:`rtsgt.interpolation.loo`); on a track too short to
        cross-validate, the marginal likelihood, with a warning. ``"likelihood"``: the maximum
        marginal likelihood of an isotropic Qc. A number: that isotropic PSD, m^2/s^3.
    max_gap_s : float
        Longest gap across which the GP answers queries, s.
    name : str
        The track's name in messages (``"prism 2"``, a file).
    prior : {"wnoa", "wnoj", "select"}
        The GP's motion prior (:mod:`rtsgt.interpolation.gp`), or ``"select"``: both fitted,
        the one whose held-out windows are predicted better kept (:func:`choose_prior`).

    Returns
    -------
    gp : GPTrack
    info : dict
        JSON-ready: ``method`` (``"loo"``, ``"likelihood"`` or ``"given"``) and, for
        ``"loo"``, the fit's statistics (``loo_log_predictive``, ``loo_knots``,
        ``loo_nees_per_dof``); ``note`` when the policy fell back to the likelihood.
    """
    if isinstance(data, PrismTrack):
        data = (data.t, data.xyz, data.cov)
    if prior == "select":
        if not isinstance(qc, str):  # a given number is a WNOA PSD
            return fit_prism_gp(data, qc, max_gap_s, name, "wnoa")
        fits = {"wnoa": fit_prism_gp(data, qc, max_gap_s, name, "wnoa")}
        try:
            fits["wnoj"] = fit_prism_gp(data, qc, max_gap_s, name, "wnoj")
        except InputError as exc:  # too short for WNOJ
            fits["wnoj"] = None, {"note": exc.bare_message}
        return choose_prior(data, fits, max_gap_s)
    if qc == "loo":
        try:
            loo = fit_qc_loo(data, mode="per-axis", max_gap_s=max_gap_s, prior=prior)
        except InputError as exc:  # too few interior measurements to cross-validate
            gp = fit_track(data, fit_qc=True, max_gap_s=max_gap_s, prior=prior)  # fails with
            # fewer than 2 (WNOA) or 3 (WNOJ) of them
            warnings.warn(f"{name}: {exc.bare_message}; Qc by the marginal likelihood instead",
                          RtsgtWarning, stacklevel=2)
            return gp, {"method": "likelihood", "note": "too few measurements for leave-one-out"}
        return fit_track(data, qc=loo.qc, max_gap_s=max_gap_s, prior=prior), {
            "method": "loo", "loo_log_predictive": loo.log_predictive,
            "loo_knots": loo.n_used, "loo_nees_per_dof": loo.nees_mean}
    if qc == "likelihood":
        return fit_track(data, fit_qc=True, max_gap_s=max_gap_s, prior=prior), {
            "method": "likelihood"}
    return fit_track(data, qc=float(qc), max_gap_s=max_gap_s, prior=prior), {"method": "given"}


def _each_prism(fit, tracks: dict[str, PrismTrack]) -> dict[str, tuple[GPTrack, dict]]:
    """``fit(pid, track)`` for every prism, in parallel threads (numpy releases the
    interpreter lock in its array operations; the result does not depend on it)."""
    with ThreadPoolExecutor(max_workers=max(1, min(len(tracks), available_cores()))) as ex:
        futures = {pid: ex.submit(fit, pid, tr) for pid, tr in tracks.items()}
        return {pid: f.result() for pid, f in futures.items()}


def fit_gps(
    tracks: dict[str, PrismTrack], options: InterpolationOptions, qc: dict[str, object] | None = None,
    info: dict[str, dict] | None = None, qc_scale: dict[str, np.ndarray] | None = None,
    prior: dict[str, str] | None = None,
) -> dict[str, GPTrack]:
    """Fit the GP of every prism track, its Qc chosen by ``options.qc`` (:func:`fit_prism_gp`)
    and, with ``options.motion_prior = "classes"`` and leave-one-out, scaled per class of the
    robot's motion (:mod:`rtsgt.interpolation.motion`; the motion comes from all the prisms'
    GPs with one Qc, fitted first).

    The motion prior is ``options.prior``: ``"wnoa"`` (the paper's) or ``"wnoj"`` for every
    track, or ``"select"``: every track is fitted with both priors, each by the whole path
    above (its own Qc, motion and class scales), and keeps the one whose held-out windows
    predict its measurements better (the higher summed log predictive density,
    :func:`rtsgt.interpolation.windows.window_score`; a tie, or no window to score, keeps
    WNOA). With a ``qc`` given as a number, ``"select"`` is WNOA (the number is a WNOA PSD).

    ``qc`` optionally gives each prism's Qc (scalar or 3x3), overriding ``options.qc``,
    ``qc_scale`` its scale per interval and ``prior`` its prior (default ``"wnoa"``):
    refitting the tracks of a written run with the Qc it found. ``info``, when given, receives
    per prism the method, the fit's statistics, ``prior`` and, with ``"select"``,
    ``prior_choice`` (per prior: ``log_density``, ``nees_per_dof``, ``windows``, ``qc``).
    """

    # what each GP is given, once for the fit with one Qc and the refit with the classes
    data = {pid: (tr.t, tr.xyz, gp_covariance(tr, options.gp_noise))
            for pid, tr in tracks.items()}
    mode = options.prior
    given = qc is not None and all(pid in qc for pid in tracks)
    if mode == "select" and (given or not isinstance(options.qc, str)):
        mode = "wnoa"  # the given Qc (and its prior, per prism) stand
    if mode != "select":
        done = _fit_with(tracks, data, options, mode, qc, qc_scale, prior)
    else:
        both = {p: _fit_with(tracks, data, options, p, qc, qc_scale, prior)
                for p in ("wnoa", "wnoj")}
        done = {pid: choose_prior(data[pid], {p: both[p][pid] for p in both},
                                  options.max_gap_s) for pid in tracks}
    if info is not None:
        info.update({pid: entry for pid, (_, entry) in done.items()})
    return {pid: gp for pid, (gp, _) in done.items()}


def choose_prior(data, fits: dict[str, tuple[GPTrack | None, dict]],
                 max_gap_s: float) -> tuple[GPTrack, dict]:
    """The fit, among one per prior, whose held-out windows have the higher summed log
    predictive density (:func:`rtsgt.interpolation.windows.window_score`; a tie, no window to
    score, or a failed WNOJ fit (``gp`` None) keep WNOA), with its info entry and
    ``prior_choice`` (``chosen`` and per prior its score and ``qc``)."""
    scores = {p: _score(data, f, max_gap_s) for p, f in fits.items()}
    ld = {p: -np.inf if v["log_density"] is None else v["log_density"]
          for p, v in scores.items()}
    chosen = "wnoj" if ld["wnoj"] > ld["wnoa"] else "wnoa"
    gp, entry = fits[chosen]
    return gp, {**entry, "prior": chosen, "prior_choice": {"chosen": chosen, **scores}}


def _score(data, fitted: tuple[GPTrack | None, dict], max_gap_s: float) -> dict:
    """The held-out windows' score of one prior's GP of a track (``log_density`` None for a
    failed fit)."""
    gp, entry = fitted
    if gp is None:
        return {"log_density": None, "nees_per_dof": None, "windows": 0,
                "measurements": 0, "note": entry.get("note", "")}
    return {**window_score(data, gp, max_gap_s), "qc": np.diag(gp.qc).tolist()}


def _fit_with(tracks: dict[str, PrismTrack], data: dict, options: InterpolationOptions,
              prior_name: str, qc: dict | None, qc_scale: dict | None,
              prior: dict | None) -> dict[str, tuple[GPTrack | None, dict]]:
    """Every prism's GP with one motion prior (:func:`fit_gps`): ``(gp, info entry)``; with
    ``"wnoj"`` in a selection, a track it cannot fit (too short) gives ``(None, entry)``."""

    def fit_one(pid: str, tr: PrismTrack) -> tuple[GPTrack, dict]:
        if qc is not None and pid in qc:
            scale = None if qc_scale is None else qc_scale.get(pid)
            p = "wnoa" if prior is None else prior.get(pid, "wnoa")
            return fit_track(data[pid], qc=qc[pid], max_gap_s=options.max_gap_s,
                             qc_scale=scale, prior=p), {"method": "given", "prior": p}
        if prior_name == "wnoj" and options.prior == "select":
            try:
                gp, entry = fit_prism_gp(data[pid], options.qc, options.max_gap_s,
                                         f"prism {pid}", prior_name)
            except InputError as exc:
                return None, {"note": exc.bare_message}
        else:
            gp, entry = fit_prism_gp(data[pid], options.qc, options.max_gap_s, f"prism {pid}",
                                     prior_name)
        return gp, {**entry, "prior": prior_name}

    done = _each_prism(fit_one, tracks)
    by_loo = [pid for pid, (_, entry) in done.items() if entry.get("method") == "loo"]
    if options.motion_prior == "classes" and by_loo:
        events = motion_events({pid: gp for pid, (gp, _) in done.items() if gp is not None})

        def refit(pid: str, tr: PrismTrack) -> tuple[GPTrack, dict]:
            gp, entry = done[pid]
            fit = fit_motion_prior(data[pid], gp.qc, events, max_gap_s=options.max_gap_s,
                                   loo_constant=entry["loo_log_predictive"], prior=gp.prior)
            entry = {**entry, "motion_prior": fit.as_dict()}
            if fit.qc_scale is None:
                return gp, entry
            return fit_track(data[pid], qc=gp.qc, max_gap_s=options.max_gap_s,
                             qc_scale=fit.qc_scale, prior=gp.prior), entry

        done.update(_each_prism(refit, {pid: tracks[pid] for pid in by_loo}))
    return done


def gp_velocities(gps: dict[str, GPTrack], t: np.ndarray) -> np.ndarray:
    """Posterior mean velocity of every prism's GP at the times ``t``, m/s, shape (T, n, 3)
    (prisms in the order of ``gps``; times across a gap are answered, as the GP would)."""
    return np.stack([g.query(t, with_velocity=True, allow_gaps=True).velocity
                     for g in gps.values()], axis=1)


def gp_velocity_z2(gps: dict[str, GPTrack], t: np.ndarray) -> np.ndarray:
    """Each prism's posterior velocity at the times ``t`` (T,) against its own covariance,
    ``v^T Cov(v)^-1 v`` (T, n) (prisms in the order of ``gps``): chi-square at three degrees
    of freedom where the prism stands and its GP is honest (docs/self-checks.md#stretches);
    NaN where the covariance is not positive definite."""
    out = np.full((np.size(t), len(gps)), np.nan)
    for i, g in enumerate(gps.values()):  # a handful of prisms
        q = g.query(t, with_velocity=True, allow_gaps=True)
        C, v = q.velocity_cov, q.velocity
        d = np.einsum("kii->ki", C)
        ok = np.all(np.isfinite(C), axis=(1, 2)) & np.all(d > 0, axis=1)
        ok[ok] = np.linalg.eigvalsh(C[ok])[:, 0] > 1e-12 * d[ok].max(axis=1)
        out[ok, i] = np.einsum("ki,ki->k", v[ok],
                               np.linalg.solve(C[ok], v[ok][:, :, None])[:, :, 0])
    return out


def query_prisms(
    tracks: dict[str, PrismTrack], gps: dict[str, GPTrack], t: np.ndarray, options: InterpolationOptions,
    coupling: StationCoupling | None = None,
) -> PrismsAtTimes:
    """Positions and covariances of every prism at the times ``t`` (inside every track).

    With ``coupling`` (and the calibration among the noise sources), the joint covariance
    across prisms is filled too (:attr:`PrismsAtTimes.cov_joint`). Not with
    ``gp_noise = "all"`` (the paper's setting): the GP has then averaged the calibration error
    with the white noise, and the full calibration covariance off the diagonal would not fit
    the smaller one left on it (the joint matrix would not be positive semi-definite).
    """
    ids = list(tracks)
    T, n = t.shape[0], len(ids)
    xyz = np.empty((T, n, 3))
    cov_gp = np.empty((T, n, 3, 3))
    nearest = np.empty((T, n))
    by_source: dict[str, np.ndarray] = {}
    systematic = SYSTEMATIC_SOURCES if options.gp_noise == "white" else ()
    for i, pid in enumerate(ids):
        q = gps[pid].query(t)
        xyz[:, i] = q.position
        cov_gp[:, i] = q.position_cov
        nearest[:, i] = q.nearest_measurement_dt
        all_sources = tuple(tracks[pid].cov_by_source)
        for s, c in _interp_cov(tracks[pid], all_sources, t).items():
            by_source.setdefault(s, np.zeros((T, n, 3, 3)))[:, i] = c
    cov = cov_gp.copy()
    for s in systematic:
        if s in by_source:
            cov += by_source[s]
    joint = None
    if (coupling is not None and coupling.cross and "calibration" in by_source
            and options.gp_noise == "white"):
        joint = joint_prism_covariance(xyz, cov, by_source["calibration"],
                                       [tracks[p].station for p in ids], coupling)
    return PrismsAtTimes(t, xyz, cov, cov_gp, by_source, nearest, joint)
