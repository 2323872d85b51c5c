"""The self-checks of a run, for either kind: the static stretches (and the plan to inflate
time-correlated noise they give) on the first fit, the others on the fit that stands.
docs/self-checks.md.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from rtsgt.checks import (
    block_cv_check,
    dynamic_calibration_check,
    gcp_fit_check,
    inter_prism_check,
    run_structure_check,
    static_noise_check,
    static_stretches,
)
from rtsgt.interpolation.gp import GPTrack
from rtsgt.interpolation.prisms import gp_velocity_z2
from rtsgt.noise.correlated import correlated_noise_plan
from rtsgt.options import RunOptions
from rtsgt.pose import ReferencePoints
from rtsgt.stages.front import Front
from rtsgt.stages.poses import PoseFit
from rtsgt.stages.prisms import PrismFit
from rtsgt.stages.timing import Progress, Stopwatch
from rtsgt.types import PrismTrack

__all__ = ["JOINT_INTER_PRISM", "run_checks", "static_noise"]


def static_noise(options: RunOptions, front: Front, fitted: dict[str, PrismTrack],
                 t: np.ndarray, xyz: np.ndarray, gps: dict[str, GPTrack], say: Progress,
                 clock: Stopwatch) -> tuple[dict[str, Any], dict[str, Any]]:
    """The noise on the static stretches of the prisms ``xyz`` (T, n, 3) at ``t`` (T,) (their
    ``gps`` test whether a slow run stands: :func:`rtsgt.checks.static_stretches`), the
    measurements ``fitted`` taken as independent (:func:`rtsgt.checks.static_noise_check`),
    and the plan to inflate the white covariance of module 2's tracks where it finds the noise
    correlated (:func:`rtsgt.noise.correlated.correlated_noise_plan`): ``(static, plan)``."""
    say("self-check: static stretches")
    stretches = static_stretches(t, xyz, gp_velocity_z2(gps, t))
    static = static_noise_check(fitted, front.origins, stretches)
    correlated = correlated_noise_plan(
        static, front.tracks, apply=options.interpolation.correlated_noise == "inflate")
    clock.lap("static_noise")
    return static, correlated


def run_checks(options: RunOptions, front: Front, static: dict[str, Any],
               fit: PoseFit | PrismFit, reference: ReferencePoints | None = None
               ) -> dict[str, Any]:
    """The self-checks of a run, JSON-ready by name: the GCP fit (of the GCP calibration beside
    a dynamic one), block cross-validation and the ``static`` check; for a pose run (a
    :class:`PoseFit` and its ``reference``) the inter-prism distances, the dynamic
    calibration's agreement (a dynamic calibration) and the inter-prism structure too; a joint
    run skips the inter-prism distances (:data:`JOINT_INTER_PRISM`) and marks the structure
    check (:func:`_joint_structure`)."""
    calib, gcp_calib = front.calibration, front.gcp_calibration
    gp_noise = options.interpolation.gp_noise
    checks: dict[str, Any] = {"gcp_fit": gcp_fit_check(calib if gcp_calib is None else gcp_calib)}
    poses = isinstance(fit, PoseFit)
    if poses and options.joint:
        checks["inter_prism_distances"] = {"skipped": JOINT_INTER_PRISM}
    elif poses:
        pr, keep, gt = fit.prisms, fit.keep, fit.groundtruth
        checks["inter_prism_distances"] = inter_prism_check(
            gt.t, gt.position, pr.xyz[keep], pr.pose_covariance[keep], pr.nearest_dt[keep],
            reference.xyz, reference.cov, reference.names, varying_cov=pr.cov_gp[keep])
    checks["block_cv"] = block_cv_check(fit.tracks, fit.gps, gp_noise=gp_noise,
                                        max_gap_s=options.interpolation.max_gap_s)
    checks["static_noise"] = static
    if poses:
        if calib.dynamic is not None:
            checks["dynamic_calibration"] = dynamic_calibration_check(calib, gcp_calib)
        checks["inter_prism_structure"] = run_structure_check(
            fit.prisms, fit.gps, fit.tracks, calib, front.coupling, reference, fit.keep,
            front.model, gp_noise)
        if options.joint:
            checks["inter_prism_structure"] = _joint_structure(
                checks["inter_prism_structure"], options.pose.clocks)
    return checks


#: Why a joint run skips the inter-prism distance check.
JOINT_INTER_PRISM = ("the joint engine holds the prisms rigid at the survey: the distances "
                     "between its prisms are not independent of its fit")


def _joint_structure(check: dict[str, Any], clocks: bool) -> dict[str, Any]:
    """The inter-prism structure check of a joint run: it judges the per-prism GPs' prisms
    (the joint engine's start), said in ``note``; with the clock states estimated, its clock
    test's verdict becomes ``"carried"`` (the one it had: ``verdict_per_prism``)."""
    out = dict(check, note="judges the residuals of the per-prism GPs' prisms, the joint "
                           "engine's start, not the joint engine's poses")
    ck = out.get("clock")
    if clocks and isinstance(ck, dict) and "verdict" in ck:
        out["clock"] = dict(ck, verdict="carried", verdict_per_prism=ck["verdict"])
    return out
