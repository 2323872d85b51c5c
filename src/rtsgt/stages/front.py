"""The stages before the GPs, for every run: module 1, the stations' calibration (by GCP, the
dynamic or the joint method), the noise model (the prism tracks in the world frame) and
module 2 (the common intervals). docs/filtering.md, docs/calibration.md, docs/noise-model.md.
"""

from __future__ import annotations

import warnings
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, replace

import numpy as np

from rtsgt.calibration import CalibrationResult, calibrate
from rtsgt.calibration.dynamic import (
    SAMPLE_STEP_S,
    DistanceSamples,
    calibrate_dynamic,
    distance_samples,
    sample_times,
)
from rtsgt.calibration.gcp import gcp_atmospheric_correction, gcp_world_positions
from rtsgt.deployment import DeploymentData
from rtsgt.errors import GeometryError, InputError, RtsgtWarning
from rtsgt.filtering import module1, module2
from rtsgt.filtering.modules import (
    FilterParams,
    FilterReport,
    RemovedMeasurements,
    removed_measurements,
    warn_tight_rate_gates,
)
from rtsgt.interpolation.prisms import fit_gps
from rtsgt.measurement.weather import check_weather_coverage
from rtsgt.noise import NoiseModel, propagate
from rtsgt.noise.coupling import StationCoupling
from rtsgt.options import RunOptions, stage_rng
from rtsgt.parallel import available_cores
from rtsgt.stages.timing import Progress, Stopwatch
from rtsgt.types import Observations, PrismTrack

__all__ = ["Front", "Removal", "calibrate_by_method", "calibrate_stations",
           "calibration_samples", "filter_module1", "noise_model", "run_front"]


@dataclass(frozen=True)
class Removal:
    """What modules 1 and 2 removed, per filtered station (in the order of module 1's kept
    observations): the raw ``observations``, module 1's reports, module 2's masks and reasons
    (indexed like module 1's kept measurements) and the stations' ``transforms``."""

    observations: Sequence[Observations]
    module1_reports: Sequence[FilterReport]
    module2_masks: Sequence[np.ndarray]
    module2_reasons: Sequence[np.ndarray]
    transforms: Mapping[str, object]

    def measurements(self, outlier_masks: Sequence[np.ndarray] | None = None
                     ) -> RemovedMeasurements:
        """The removed measurements in the world frame, with those the windows of distance
        rejections left out (``outlier_masks``, indexed like module 2's kept) where given
        (:func:`rtsgt.filtering.modules.removed_measurements`)."""
        return removed_measurements(self.observations, self.module1_reports,
                                    self.module2_masks, self.module2_reasons, self.transforms,
                                    outlier_masks)


@dataclass(frozen=True)
class Front:
    """What the stages before the GPs give, for either kind of run.

    ``reports``: the filter reports by stage (``input``, ``module1_station<id>``,
    ``module2``); ``weather_coverage`` (None without weather); ``model``: the noise model;
    ``calibration`` the run uses and ``gcp_calibration`` beside a dynamic or joint one
    (:func:`calibrate_by_method`); ``coupling`` of the stations' calibration errors;
    ``gcp_world``: the GCPs' world positions by name, m; ``filtered``: module 1's kept
    observations per station; ``tracks``: module 2's tracks by prism (world frame);
    ``intervals`` (K, 2), s; ``removal`` and ``removed``: what modules 1 and 2 removed.
    """

    reports: dict[str, object]
    weather_coverage: dict | None
    model: NoiseModel
    calibration: CalibrationResult
    gcp_calibration: CalibrationResult | None
    coupling: StationCoupling
    gcp_world: dict[str, np.ndarray]
    filtered: list[Observations]
    tracks: dict[str, PrismTrack]
    intervals: np.ndarray
    removal: Removal
    removed: RemovedMeasurements

    @property
    def origins(self) -> dict[str, np.ndarray]:
        """The stations' positions in the world frame, m (3,) each."""
        return {s: np.asarray(T.translation, dtype=float)
                for s, T in self.calibration.transforms.items()}


def noise_model(data: DeploymentData, options: RunOptions) -> NoiseModel:
    """The noise model of a run: the options' one, or every source with the deployment's
    instrument."""
    return options.noise if options.noise is not None else NoiseModel(instrument=data.instrument)


def calibrate_stations(data: DeploymentData, options: RunOptions,
                       t_start: float) -> CalibrationResult:
    """The extrinsic calibration of a run (its own random stream, ``"calibration"``): the GCP
    shots with the atmospheric correction (the weather at ``t_start``, the start of tracking,
    for shots outside the weather series), fitted by :func:`rtsgt.calibration.calibrate`.
    ``rtsgt plan`` calls it to get the very calibration a run of the deployment gets."""
    gcp = gcp_atmospheric_correction(data.gcp, noise_model(data, options), data.weather, t_start)
    return calibrate(gcp, reference_station=data.reference_station,
                     instrument=data.instrument, samples=options.pose.samples,
                     rng=stage_rng(options.seed, "calibration"),
                     model=options.calibration.model,
                     weighting=options.calibration.weighting)


def calibration_samples(data: DeploymentData, filtered: list[Observations], model: NoiseModel,
                        options: RunOptions, step_s: float = SAMPLE_STEP_S) -> DistanceSamples:
    """The observations of the dynamic calibration (:mod:`rtsgt.calibration.dynamic`): each
    station's filtered observations as a track in its own frame (first-order noise model, the
    instrument, tilt and atmosphere sources), module 2's common intervals, each track's GP
    (the run's interpolation options, given the white sources), sampled every ``step_s`` s.
    The scale error shared by the tracks is the atmosphere source's: its variance
    ``tr(C_atm) / d^2`` averaged over the measurements."""
    station_model = model.with_sources(
        [s for s in model.sources if s in ("instrument", "tilt", "atmosphere")])
    tracks = {obs.prism: propagate(obs, station_model, weather=data.weather) for obs in filtered}
    kept, intervals, _ = module2(list(tracks.values()), options.filter)
    tracks = {tr.prism: tr for tr in kept}
    gps = fit_gps(tracks, replace(options.interpolation, gp_noise="white"))
    t = sample_times(gps, intervals, step_s)
    scale = [np.trace(tr.cov_by_source["atmosphere"], axis1=1, axis2=2) / tr.range_m ** 2
             for tr in tracks.values() if "atmosphere" in tr.cov_by_source]
    return distance_samples(gps, {o.prism: o.station for o in filtered}, data.reference, t,
                            scale_variance=float(np.mean(np.concatenate(scale))) if scale else 0.0)


def calibrate_by_method(
    data: DeploymentData, options: RunOptions, filtered: list[Observations],
) -> tuple[CalibrationResult, CalibrationResult | None]:
    """The stations' calibration of a run by ``options.calibration.method``, from the stage's
    random stream: :func:`calibrate_stations` for ``"gcp"``; for ``"dynamic"`` and ``"joint"``,
    :func:`rtsgt.calibration.dynamic.calibrate_dynamic` on :func:`calibration_samples` of the
    filtered observations (with the corrected GCP shots for ``"joint"``).

    Returns the calibration the run uses and, for ``"dynamic"`` and ``"joint"``, the GCP
    calibration of the same deployment (``"dynamic"``: with its Monte Carlo covariance, for the
    agreement check; None when the GCP shots cannot calibrate the stations); None for
    ``"gcp"``.
    """
    opt = options.calibration
    t_start = min(float(o.t[0]) for o in filtered)
    if opt.method == "gcp":
        return calibrate_stations(data, options, t_start), None
    model = noise_model(data, options)
    rng = stage_rng(options.seed, "calibration")
    gcp = gcp_atmospheric_correction(data.gcp, model, data.weather, t_start)
    kw = {"reference_station": data.reference_station, "instrument": data.instrument,
          "model": opt.model}
    samples = calibration_samples(data, filtered, model, options)
    dyn = {"engine": options.noise_engine, "n_samples": options.pose.samples,
           "gate_m": options.pose.distance_gate_m, **kw}
    if opt.method == "joint":
        gcp_calib = calibrate(gcp, samples=0, weighting=opt.weighting, **kw)
        return calibrate_dynamic(samples, gcp=gcp, gcp_calibration=gcp_calib, rng=rng,
                                 **dyn), gcp_calib
    try:
        gcp_calib = calibrate(gcp, samples=options.pose.samples, rng=rng,
                              weighting=opt.weighting, **kw)
    except (InputError, GeometryError) as exc:
        warnings.warn(f"dynamic calibration: the GCP shots cannot calibrate the stations "
                      f"({exc}); no comparison with the GCP calibration", RtsgtWarning,
                      stacklevel=2)
        gcp_calib = None
    return calibrate_dynamic(samples, rng=rng, **dyn), gcp_calib


def filter_module1(data: DeploymentData, params: FilterParams
                   ) -> tuple[list[Observations], dict[str, object], list[FilterReport]]:
    """Module 1 on every station's observations: the kept observations (at least 2 each,
    else InputError naming the file), the reports by stage (the reader's ``input`` report
    first, where it has one) and module 1's reports in the order of the stations."""
    filtered, reports, reports1 = [], {}, []
    if data.input_report is not None:  # what the reader removed (a bag's statuses)
        reports["input"] = data.input_report
    for obs in data.observations:
        kept, rep = module1(obs, params)
        if len(kept) < 2:
            raise InputError(
                f"station {obs.station}: fewer than 2 measurements left after module 1", obs.source
            )
        filtered.append(kept)
        reports[f"module1_station{obs.station}"] = rep
        reports1.append(rep)
        warn_tight_rate_gates(obs, rep, params)
    return filtered, reports, reports1


def world_tracks(data: DeploymentData, options: RunOptions, model: NoiseModel,
                 calib: CalibrationResult, filtered: list[Observations]) -> dict[str, PrismTrack]:
    """Each station's filtered observations through the noise model into the world frame, by
    prism (the run's noise engine and its ``"noise"`` random stream); InputError for a
    station without calibration."""
    tracks: dict[str, PrismTrack] = {}
    noise_rng = stage_rng(options.seed, "noise")
    for obs in filtered:
        if obs.station not in calib.transforms:
            raise InputError(
                f"station {obs.station} tracks prism {obs.prism} but has no GCP calibration; "
                f"calibrated stations: {', '.join(sorted(calib.transforms))}", obs.source
            )
        tracks[obs.prism] = propagate(
            obs, model, T_world_station=calib.transforms[obs.station], weather=data.weather,
            engine=options.noise_engine, samples=options.pose.samples, rng=noise_rng,
            workers=available_cores(),  # the same numbers on any number (one stream per chunk)
        )
    return tracks


def run_front(data: DeploymentData, options: RunOptions, say: Progress,
              clock: Stopwatch) -> Front:
    """Module 1, the calibration, the noise model and module 2 (the stages of every run),
    each timed on ``clock``."""
    say("filtering (module 1)")
    filtered, reports, reports1 = filter_module1(data, options.filter)
    weather_coverage = None if data.weather is None else check_weather_coverage(
        data.weather, np.concatenate([o.t for o in filtered]))
    clock.lap("filter_module1")

    say("extrinsic calibration")
    model = noise_model(data, options)
    calib, gcp_calib = calibrate_by_method(data, options, filtered)
    gcp_xyz, gcp_names = gcp_world_positions(data.gcp, calib.transforms)
    gcp_world = {} if gcp_xyz is None else dict(zip(gcp_names, gcp_xyz, strict=True))
    clock.lap("calibration")

    say("noise model")
    tracks = world_tracks(data, options, model, calib, filtered)
    clock.lap("noise_model")

    say("common intervals (module 2)")
    kept_tracks, intervals, rep2 = module2(list(tracks.values()), options.filter)
    reports["module2"] = rep2
    # module 2's masks per prism (one prism per station), indexed like module 1's kept
    kept2 = dict(zip(tracks, zip(rep2.kept_masks, rep2.reasons, strict=True), strict=True))
    removal = Removal(data.observations, reports1, [kept2[o.prism][0] for o in filtered],
                      [kept2[o.prism][1] for o in filtered], calib.transforms)
    removed = removal.measurements()
    clock.lap("filter_module2")
    return Front(reports, weather_coverage, model, calib, gcp_calib,
                 StationCoupling.from_calibration(calib), gcp_world, filtered,
                 {tr.prism: tr for tr in kept_tracks}, intervals, removal, removed)
