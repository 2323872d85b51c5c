"""The ground-truth pipeline: from a deployment's data to poses with covariance.

Stages (data flows one way; nothing here reads files or prints)::

    observations per station --module 1--> filtered observations
    GCP shots --> extrinsic calibration (+ Monte Carlo samples of every station transform)
    filtered observations + calibration + weather --noise model--> prism tracks (world frame)
    prism tracks --module 2--> common intervals --GP per prism--> prisms at the query times
    prisms + reference prisms on the robot --registration--> poses with 6x6 covariance
    poses --module 4 gates--> kept poses

How the noise sources enter the GP
----------------------------------
The GP treats measurement noise as independent from one measurement to the next. That is true
of the instrument and tilt-compensator errors ("white" sources), but not of the others: the
extrinsic calibration error is one draw for the whole deployment, a station's clock offset is
constant, and the atmospheric error changes over hours. Feeding those into the GP as if they
were independent would let the smoother average them away over many measurements and report
an over-confident track. rtsgt therefore fits the GP with the white covariance only and adds
the covariance of the *systematic* sources (interpolated at the query time from the
neighbouring measurements) to the interpolated position afterwards. ``gp_noise="all"``
reproduces the paper, which fed the total covariance to the GP.

Qc is chosen by leave-one-out cross-validation per axis (:mod:`rtsgt.interpolation.loo`):
the ground truth is an interpolation, and the marginal likelihood, which scores predictions,
overstates its error.

Errors shared between prisms
----------------------------
Two stations calibrated from the same reference shots have correlated calibration errors
(:class:`StationCoupling`); the pose engines get the joint (3n x 3n) covariance of the prisms
(:func:`joint_prism_covariance`), since errors that move the prisms together are not averaged
out by the registration. On simulated deployments this took the position NEES / dof from
1.15-1.25 to 1.11-1.12 (README, section Honesty).

Checks that warn
----------------
A run says what it cannot vouch for as :class:`~rtsgt.errors.RtsgtWarning` (recorded in
:attr:`RunResult.warnings`, hence ``summary.json``): a weather record that does not cover the
measurement times (:func:`rtsgt.io.weather.check_weather_coverage`), a surveyed inter-prism
distance that the tracked distances disagree with beyond its predicted sigma
(:func:`rtsgt.filtering.gates.surveyed_distance_check`), rate gates that reject motion.
"""

from __future__ import annotations

import os
import time
import warnings
from collections.abc import Callable
from dataclasses import dataclass, field, replace

import numpy as np

from rtsgt.calibration import CalibrationResult, calibrate
from rtsgt.errors import InputError, RtsgtWarning
from rtsgt.filtering import FilterParams, module1, module2
from rtsgt.filtering.gates import GateReport, apply_gates, surveyed_distance_check
from rtsgt.geometry.so3 import matrix_to_quat_xyzw
from rtsgt.interpolation import GPTrack, fit_track
from rtsgt.interpolation.loo import fit_qc_loo
from rtsgt.io.weather import check_weather_coverage
from rtsgt.measurement.instruments import InstrumentProfile
from rtsgt.noise import NoiseModel, propagate
from rtsgt.pose import PoseEstimate, ReferencePoints, estimate_poses
from rtsgt.types import GcpShots, Observations, PoseTrajectory, PrismTrack, WeatherSeries

#: Noise sources whose errors are independent between measurements (fed to the GP).
WHITE_SOURCES = ("instrument", "tilt")
#: Noise sources whose errors are shared by many measurements (added after the GP).
SYSTEMATIC_SOURCES = ("atmosphere", "time_sync", "calibration")
#: How Qc is chosen when not given as a number (see :func:`fit_gps`).
QC_METHODS = ("loo", "likelihood")

Progress = Callable[[str], None]


@dataclass(frozen=True)
class DeploymentData:
    """Everything a deployment provides, already read and validated (no file access after).

    Attributes
    ----------
    name : str
    instrument : InstrumentProfile
    observations : tuple of Observations
        One per station; station ``obs.station`` tracks prism ``obs.prism``.
    gcp : GcpShots
    reference : ReferencePoints
        Reference prisms in the body frame, with covariance.
    reference_station : str
        The world frame is this station's frame.
    weather : WeatherSeries, optional
    query_times : ndarray, optional
        Times (s) at which to compute poses; otherwise a regular grid at ``rate_hz``.
    """

    name: str
    instrument: InstrumentProfile
    observations: tuple[Observations, ...]
    gcp: GcpShots
    reference: ReferencePoints
    reference_station: str = "1"
    weather: WeatherSeries | None = None
    query_times: np.ndarray | None = None


@dataclass(frozen=True)
class RunOptions:
    """Processing parameters of one run (defaults: the paper's where it has one)."""

    engine: str = "mc"
    samples: int = 1000
    seed: int = 0
    rate_hz: float = 5.0
    qc: float | str = "loo"
    max_gap_s: float = 3.0
    noise: NoiseModel | None = None
    filter: FilterParams = field(default_factory=FilterParams)
    distance_gate_m: float = 0.10
    uncertainty_gate_m: float = 0.20
    gp_noise: str = "white"

    def __post_init__(self) -> None:
        if self.engine not in ("mc", "ut", "linear"):
            raise InputError(f"Expected engine mc, ut or linear, got {self.engine!r}")
        if isinstance(self.samples, bool) or not isinstance(self.samples, (int, np.integer)) \
                or self.samples < 10:
            raise InputError(f"Expected an integer of at least 10 samples, got {self.samples!r}")
        if not (np.isfinite(self.rate_hz) and self.rate_hz > 0):
            raise InputError(f"Expected a finite rate_hz > 0 Hz, got {self.rate_hz!r}")
        for name in ("max_gap_s", "distance_gate_m", "uncertainty_gate_m"):
            value = getattr(self, name)
            if not value > 0:  # infinity switches the limit off; nan is refused
                raise InputError(f"Expected {name} > 0, got {value!r}")
        if isinstance(self.qc, str) and self.qc not in QC_METHODS:
            raise InputError(
                f"Expected qc {', '.join(QC_METHODS)} or a number (m^2/s^3), got {self.qc!r}")
        if not isinstance(self.qc, str) and not (np.isfinite(self.qc) and self.qc > 0):
            raise InputError(f"Expected qc > 0 m^2/s^3, got {self.qc!r}")
        if self.gp_noise not in ("white", "all"):
            raise InputError(f"Expected gp_noise 'white' or 'all', got {self.gp_noise!r}")

    @property
    def noise_engine(self) -> str:
        """The per-measurement engine: Monte Carlo for the MC pose engine, else first order."""
        return "mc" if self.engine == "mc" else "linear"


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


@dataclass(frozen=True)
class RunResult:
    """Everything a run computed; the writers in :mod:`rtsgt.io.run_output` turn it into files."""

    data: DeploymentData
    options: RunOptions
    filter_reports: dict[str, object]
    calibration: CalibrationResult
    tracks: dict[str, PrismTrack]
    intervals: np.ndarray
    gps: dict[str, GPTrack]
    prisms: PrismsAtTimes
    estimate: PoseEstimate
    keep: np.ndarray
    gate_report: GateReport
    groundtruth: PoseTrajectory
    noise_model: NoiseModel
    timings_s: dict[str, float]
    qc_info: dict[str, dict] = field(default_factory=dict)
    coupling: StationCoupling | None = None
    #: Every warning of the run (:class:`~rtsgt.errors.RtsgtWarning` and other
    #: :class:`UserWarning`), once each, in order (``summary.json`` ``warnings``).
    warnings: list[str] = field(default_factory=list)
    #: :func:`rtsgt.io.weather.weather_coverage` of the filtered measurements (None: no weather).
    weather_coverage: dict | None = None
    #: :func:`rtsgt.filtering.gates.surveyed_distance_check` of the kept poses, per prism pair.
    distance_check: dict = field(default_factory=dict)

    @property
    def rejection_reasons(self) -> np.ndarray:
        """Per queried pose: ``""`` when kept, else the first gate it failed."""
        return self.gate_report.reason

    @property
    def prism_ids(self) -> list[str]:
        return [o.prism for o in self.data.observations]


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


#: Share of a station's measurements that module 1 may reject for their rates before rtsgt
#: warns that the gates look too tight for the robot (outliers are rare; motion is not).
RATE_REJECTION_WARNING = 0.10


def warn_tight_rate_gates(obs: Observations, report, params: FilterParams) -> None:
    """Warn when module 1's rate gates remove much of a station's series.

    The paper's gates (1 deg/s) suit a slow robot far from the stations; a robot at 2 m/s,
    10 m from a station, turns the line of sight by 11 deg/s, and the gates then reject true
    motion, not outliers: say so, with the numbers to change.
    """
    n_rate = sum(int(report.removed.get(k, 0)) for k in ("rate_distance", "rate_hz", "rate_v"))
    if report.n_in and n_rate / report.n_in > RATE_REJECTION_WARNING:
        warnings.warn(
            f"station {obs.station}: module 1 rejected {n_rate} of {report.n_in} measurements "
            f"({100 * n_rate / report.n_in:.0f} %) for their rate of change (gates "
            f"tau_r = {params.tau_r:g} m/s, tau_a = {np.degrees(params.tau_a):g} deg/s, "
            f"tau_e = {np.degrees(params.tau_e):g} deg/s): that is motion, not outliers, if the "
            "robot is fast or close to the station; raise the [filter] gates of the "
            "configuration", RtsgtWarning, stacklevel=3)


def gcp_atmospheric_correction(
    gcp: GcpShots, model: NoiseModel, weather: WeatherSeries | None, fallback_t: float
) -> GcpShots:
    """GCP shots with the first-velocity correction applied to their distances.

    The GCP distances need the same atmospheric correction as the tracking distances: at
    100 m, the 5-10 ppm of a cold, high site is 0.5-1 mm of scale between stations, a bias of
    the calibration that no covariance accounts for. Each shot takes the weather at its time
    when that time lies inside the weather series, else the weather at ``fallback_t`` (the
    start of tracking): a station whose clock was off (the GCP shots of station 1 in the
    2022-11-10 data are months off) must not pick the weather of another season. Without
    weather, the shots are returned unchanged (reference atmosphere, as for the tracks).
    """
    if weather is None:
        return gcp
    from rtsgt.measurement.atmosphere import instrument_correction_ppm

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


def fit_gps(
    tracks: dict[str, PrismTrack], options: RunOptions, qc: dict[str, object] | None = None,
    info: dict[str, dict] | None = None,
) -> dict[str, GPTrack]:
    """Fit the GP of every prism track, its Qc chosen by ``options.qc``.

    ``"loo"`` (default): leave-one-out cross-validation of a diagonal Qc (one PSD per world
    axis), which calibrates the GP for interpolation (:mod:`rtsgt.interpolation.loo`);
    ``"likelihood"``: the marginal likelihood; a number: that isotropic PSD, m^2/s^3. ``qc``
    optionally gives each prism's Qc (scalar or 3x3), overriding ``options.qc``: refitting the
    tracks of a written run with the Qc it found. ``info``, when given, receives per prism the
    method and the fit's statistics. The prisms are fitted in parallel threads (numpy releases
    the interpreter lock in its array operations); the result does not depend on it.
    """

    def fit_one(pid: str, tr: PrismTrack) -> tuple[GPTrack, dict]:
        data = (tr.t, tr.xyz, gp_covariance(tr, options.gp_noise))
        if qc is not None and pid in qc:
            return fit_track(data, qc=qc[pid], max_gap_s=options.max_gap_s), {"method": "given"}
        if options.qc == "loo":
            try:
                loo = fit_qc_loo(data, mode="per-axis", max_gap_s=options.max_gap_s)
            except InputError as exc:  # too few interior measurements to cross-validate
                warnings.warn(f"prism {pid}: {exc.bare_message}; Qc by the marginal "
                              "likelihood instead", RtsgtWarning, stacklevel=2)
                return fit_track(data, fit_qc=True, max_gap_s=options.max_gap_s), {
                    "method": "likelihood", "note": "too few measurements for leave-one-out"}
            return fit_track(data, qc=loo.qc, max_gap_s=options.max_gap_s), {
                "method": "loo", "loo_log_predictive": loo.log_predictive,
                "loo_knots": loo.n_used, "loo_nees_per_dof": loo.nees_mean}
        if options.qc == "likelihood":
            return fit_track(data, fit_qc=True, max_gap_s=options.max_gap_s), {
                "method": "likelihood"}
        return fit_track(data, qc=float(options.qc), max_gap_s=options.max_gap_s), {
            "method": "given"}

    from concurrent.futures import ThreadPoolExecutor

    with ThreadPoolExecutor(max_workers=max(1, min(len(tracks), os.cpu_count() or 1))) as ex:
        futures = {pid: ex.submit(fit_one, pid, tr) for pid, tr in tracks.items()}
        done = {pid: f.result() for pid, f in futures.items()}
    if info is not None:
        info.update({pid: entry for pid, (_, entry) in done.items()})
    return {pid: gp for pid, (gp, _) in done.items()}


@dataclass(frozen=True)
class StationCoupling:
    """How the calibration errors of different stations are correlated.

    Every station is fitted to the reference station's shots of the same markers, so the
    errors of two calibrated stations share the reference's measurement noise: their left
    perturbations ``xi_a``, ``xi_b`` (:mod:`rtsgt.geometry.transform`) are correlated, and so
    are the errors of the prisms they track. The pose engines need that correlation: it moves
    the prisms together, which a registration cannot average out.

    Attributes
    ----------
    origin : dict str -> ndarray (3,)
        World position of each station, m (the lever arm of its rotation error).
    cross : dict (str, str) -> ndarray (6, 6)
        ``Cov(xi_a, xi_b)`` for pairs of stations (``a <= b``, ``a == b`` included: one
        sample covariance, so the joint matrix is positive semi-definite), m^2 / m rad / rad^2.
    """

    origin: dict[str, np.ndarray]
    cross: dict[tuple[str, str], np.ndarray]

    @classmethod
    def from_calibration(cls, calib: CalibrationResult) -> StationCoupling:
        """From the calibration's Monte Carlo samples (sample m of every station comes from
        the same perturbed GCP shots)."""
        from rtsgt.geometry.transform import perturbation

        xi = {}
        for sid, T in calib.transforms.items():
            if T.samples_rotation is None or T.samples_translation is None:
                continue
            d = perturbation(T.rotation, T.translation, T.samples_rotation,
                             T.samples_translation)
            xi[sid] = d - d.mean(axis=0)
        cross = {}
        ids = sorted(xi)
        for i, a in enumerate(ids):
            for b in ids[i:]:  # (a, a) too: the joint matrix is then one sample covariance
                m = xi[a].shape[0]
                if m > 1 and m == xi[b].shape[0]:
                    cross[(a, b)] = xi[a].T @ xi[b] / (m - 1)
        origin = {sid: np.asarray(T.translation, dtype=float)
                  for sid, T in calib.transforms.items()}
        return cls(origin, cross)

    def to_dict(self) -> dict:
        """JSON-ready (pairs keyed ``"a|b"``)."""
        return {"origin_m": {k: v.tolist() for k, v in self.origin.items()},
                "cross_covariance": {f"{a}|{b}": c.tolist() for (a, b), c in self.cross.items()}}

    @classmethod
    def from_dict(cls, doc: dict) -> StationCoupling:
        origin = {str(k): np.asarray(v, dtype=float) for k, v in doc["origin_m"].items()}
        cross = {}
        for key, c in doc["cross_covariance"].items():
            a, b = str(key).split("|")
            cross[(a, b)] = np.asarray(c, dtype=float).reshape(6, 6)
        return cls(origin, cross)

    def block(self, a: str, b: str) -> np.ndarray | None:
        """``Cov(xi_a, xi_b)``, or None when unknown."""
        if (a, b) in self.cross:
            return self.cross[(a, b)]
        if (b, a) in self.cross:
            return self.cross[(b, a)].T
        return None

    def prism_covariance(
        self, xyz_a: np.ndarray, xyz_b: np.ndarray, stations: list[str]
    ) -> np.ndarray:
        """(T, 3n, 3n) calibration part of ``Cov(q(a), q(b))`` for prisms at two positions.

        Block ``(i, j)`` is ``J_i(a) Cov(xi_s_i, xi_s_j) J_j(b)^T`` with ``J = [I, -[q]x]``
        and ``q`` the prism's position relative to its station (world axes), the Jacobian of
        the calibration source (:func:`rtsgt.noise.linear.calibration_covariance`); zero where
        the coupling is unknown. ``xyz_a``, ``xyz_b``: (T, n, 3) m; ``stations``: the station
        of each prism.
        """
        from rtsgt.geometry.so3 import hat

        T, n, _ = xyz_a.shape
        eye = np.broadcast_to(np.eye(3), (T, 3, 3))

        def jac(xyz):
            return [np.concatenate([eye, -hat(xyz[:, i] - self.origin.get(s, np.zeros(3)))],
                                   axis=-1) for i, s in enumerate(stations)]

        Ja, Jb = jac(xyz_a), jac(xyz_b)
        out = np.zeros((T, 3 * n, 3 * n))
        for i in range(n):
            for j in range(n):
                X = self.block(stations[i], stations[j])
                if X is not None:
                    out[:, 3 * i:3 * i + 3, 3 * j:3 * j + 3] = Ja[i] @ X @ np.swapaxes(Jb[j], 1, 2)
        return out


def joint_prism_covariance(
    xyz: np.ndarray, cov: np.ndarray, cov_calibration: np.ndarray, stations: list[str],
    coupling: StationCoupling,
) -> np.ndarray:
    """(T, 3n, 3n) joint covariance of the prisms, the calibration part taken jointly.

    ``cov`` (T, n, 3, 3) is each prism's total, ``cov_calibration`` its calibration part. For
    every prism whose station the coupling knows, the calibration part is replaced by the
    joint one of :meth:`StationCoupling.prism_covariance` (``i == j`` included): one sample
    covariance of the stacked station perturbations, so the result is positive
    semi-definite by construction.
    """
    from rtsgt.pose.reference import block_diagonal

    known = [coupling.block(s, s) is not None for s in stations]
    rest = np.where(np.array(known)[None, :, None, None], cov - cov_calibration, cov)
    out = block_diagonal(rest) + coupling.prism_covariance(xyz, xyz, stations)
    return 0.5 * (out + np.swapaxes(out, 1, 2))


def query_prisms(
    tracks: dict[str, PrismTrack], gps: dict[str, GPTrack], t: np.ndarray, options: RunOptions,
    coupling: StationCoupling | None = None,
) -> PrismsAtTimes:
    """Positions and covariances of every prism at the times ``t`` (inside every track).

    With ``coupling`` (and the calibration among the noise sources), the joint covariance
    across prisms is filled too (:attr:`PrismsAtTimes.cov_joint`).
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
    if coupling is not None and coupling.cross and "calibration" in by_source:
        joint = joint_prism_covariance(xyz, cov, by_source["calibration"],
                                       [tracks[p].station for p in ids], coupling)
    return PrismsAtTimes(t, xyz, cov, cov_gp, by_source, nearest, joint)


def run_pipeline(
    data: DeploymentData, options: RunOptions | None = None, progress: Progress | None = None
) -> RunResult:
    """Compute the ground truth of a deployment.

    Parameters
    ----------
    data : DeploymentData
    options : RunOptions, optional
    progress : callable, optional
        Called with the name of each stage as it starts (for progress displays).

    Returns
    -------
    RunResult
        With :attr:`RunResult.warnings`: every :class:`UserWarning` (the
        :class:`~rtsgt.errors.RtsgtWarning` of the checks included) the stages raised, once
        each. They are recorded while the stages run and then issued again, once each, so a
        caller (the CLI's ``warning: ...`` lines) sees every one once, even if the run fails.
    """
    caught: list[warnings.WarningMessage] = []
    try:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")  # a second run must record what the first did
            result = _run_stages(data, options, progress)
    finally:
        said = _reissue(caught)
    return replace(result, warnings=said)


def _reissue(caught: list[warnings.WarningMessage]) -> list[str]:
    """Issue recorded warnings again, once each; the texts of the user warnings among them."""
    seen: set[tuple[type, str]] = set()
    said: list[str] = []
    for w in caught:
        key = (w.category, str(w.message))
        if key in seen:
            continue
        seen.add(key)
        warnings.warn_explicit(w.message, w.category, w.filename, w.lineno, source=w.source)
        if issubclass(w.category, UserWarning):
            said.append(str(w.message))
    return said


def _run_stages(
    data: DeploymentData, options: RunOptions | None, progress: Progress | None
) -> RunResult:
    """The stages of :func:`run_pipeline` (their warnings not yet recorded)."""
    options = RunOptions() if options is None else options
    say = progress or (lambda stage: None)
    rng = np.random.default_rng(options.seed)
    timings: dict[str, float] = {}
    tick = time.perf_counter()

    def lap(name: str) -> None:
        nonlocal tick
        now = time.perf_counter()
        timings[name] = now - tick
        tick = now

    say("filtering (module 1)")
    fparams = options.filter
    filtered, reports = [], {}
    for obs in data.observations:
        kept, rep = module1(obs, fparams)
        if len(kept) < 2:
            raise InputError(
                f"station {obs.station}: fewer than 2 measurements left after module 1", obs.source
            )
        filtered.append(kept)
        reports[f"module1_station{obs.station}"] = rep
        warn_tight_rate_gates(obs, rep, fparams)
    weather_coverage = None if data.weather is None else check_weather_coverage(
        data.weather, np.concatenate([o.t for o in filtered]))
    lap("filter_module1")

    say("extrinsic calibration")
    model = options.noise if options.noise is not None else NoiseModel(instrument=data.instrument)
    t_start = min(float(o.t[0]) for o in filtered)
    gcp = gcp_atmospheric_correction(data.gcp, model, data.weather, t_start)
    calib = calibrate(gcp, reference_station=data.reference_station,
                      instrument=data.instrument, samples=options.samples, rng=rng)
    lap("calibration")

    say("noise model")
    tracks: dict[str, PrismTrack] = {}
    for obs in filtered:
        if obs.station not in calib.transforms:
            raise InputError(
                f"station {obs.station} tracks prism {obs.prism} but has no GCP calibration; "
                f"calibrated stations: {', '.join(sorted(calib.transforms))}", obs.source
            )
        tracks[obs.prism] = propagate(
            obs, model, T_world_station=calib.transforms[obs.station], weather=data.weather,
            engine=options.noise_engine, samples=options.samples, rng=rng,
        )
    lap("noise_model")

    say("common intervals (module 2)")
    kept_tracks, intervals, rep2 = module2(list(tracks.values()), fparams)
    reports["module2"] = rep2
    tracks = {tr.prism: tr for tr in kept_tracks}
    lap("filter_module2")

    say("GP interpolation")
    qc_info: dict[str, dict] = {}
    gps = fit_gps(tracks, options, info=qc_info)
    if data.query_times is not None:
        t_query = np.asarray(data.query_times, dtype=float)
        inside = np.zeros(t_query.shape, bool)
        for a, b in intervals:
            inside |= (t_query >= a) & (t_query <= b)
        t_query = t_query[inside]
    else:
        t_query = query_grid(intervals, options.rate_hz)
    # queries across a gap longer than max_gap_s in any prism are not poses we can vouch for
    ok = np.ones(t_query.shape, bool)
    for g in gps.values():
        ok &= g.supported(t_query)
    t_query = t_query[ok]
    if t_query.size == 0:
        raise InputError("No query time falls inside the intervals common to all prisms")
    coupling = StationCoupling.from_calibration(calib)
    prisms = query_prisms(tracks, gps, t_query, options, coupling)
    lap("interpolation")

    say("poses")
    reference = data.reference.select(list(tracks))
    est = estimate_poses(prisms.xyz, prisms.pose_covariance, reference, engine=options.engine,
                         samples=options.samples, rng=rng)
    lap("pose")

    say("quality gates (module 4)")
    keep, gate_report = apply_gates(
        est, reference, distance_gate_m=options.distance_gate_m,
        uncertainty_gate_m=options.uncertainty_gate_m,
    )
    gt = PoseTrajectory(
        t_query[keep], est.t[keep], matrix_to_quat_xyzw(est.R[keep]), est.cov[keep]
    )
    # a surveyed distance the tracking disagrees with biases every pose: say so
    distance_check = surveyed_distance_check(
        prisms.xyz[keep], prisms.pose_covariance[keep], reference.xyz, reference.cov,
        reference.names)
    lap("gates")
    return RunResult(data, options, reports, calib, tracks, intervals, gps, prisms, est, keep,
                     gate_report, gt, model, timings, qc_info, coupling,
                     weather_coverage=weather_coverage, distance_check=distance_check)
