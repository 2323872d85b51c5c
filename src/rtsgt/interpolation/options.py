"""The options of the GP interpolation stage, :class:`InterpolationOptions` (TOML
``[interpolation]``), and the names of its switches; :mod:`rtsgt.options` holds it in a run's
options (docs/interpolation.md, docs/file-formats.md#deployment-toml).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal, get_args

import numpy as np

from rtsgt.choices import DEFAULT_MAX_GAP_S, DEFAULT_PRIOR, DEFAULT_QC
from rtsgt.errors import InputError

__all__ = ["CORRELATED_NOISE", "GP_NOISE", "MOTION_PRIORS", "OUTLIER_WINDOWS", "PRIOR_CHOICES",
           "QC_METHODS", "InterpolationOptions", "one_of"]

#: How Qc is chosen when not given as a number (see :func:`rtsgt.interpolation.prisms.fit_gps`).
QcMethod = Literal["loo", "likelihood"]
QC_METHODS: tuple[str, ...] = get_args(QcMethod)
#: What the GP is given: the white noise sources only (rtsgt), or every source (the paper).
GpNoise = Literal["white", "all"]
GP_NOISE: tuple[str, ...] = get_args(GpNoise)
MotionPrior = Literal["classes", "constant"]
MOTION_PRIORS: tuple[str, ...] = get_args(MotionPrior)
#: What the GPs do with the measurements inside the windows of distance rejections: leave them
#: out and fit again (rtsgt), or keep them (the paper).
OutlierWindows = Literal["remove", "keep"]
OUTLIER_WINDOWS: tuple[str, ...] = get_args(OutlierWindows)
#: The GP's motion prior: white noise on the acceleration (the paper's), on the jerk, or the
#: one of the two whose held-out windows each track predicts better.
MotionModel = Literal["select", "wnoa", "wnoj"]
PRIOR_CHOICES: tuple[str, ...] = get_args(MotionModel)

#: What the GPs do with the time-correlated noise the static-stretch check finds: inflate the
#: white covariance by the loss of independent samples (rtsgt), or take the measurements as
#: independent (the paper).
CorrelatedNoise = Literal["inflate", "ignore"]
CORRELATED_NOISE: tuple[str, ...] = get_args(CorrelatedNoise)


def one_of(name: str, value, choices: tuple[str, ...]) -> None:
    """Refuse ``value`` unless it is one of ``choices``, naming them."""
    if value not in choices:
        raise InputError(f"Expected {name} {' or '.join(map(repr, choices))}, got {value!r}")


@dataclass(frozen=True)
class InterpolationOptions:
    """Query times and the GP of each prism (TOML ``[interpolation]``; docs/interpolation.md).

    ``rate_hz``: the query grid, Hz (without the deployment's query times); ``qc``: the GP's PSD,
    m^2/s^3, or how to choose it per prism (``"loo"``, ``"likelihood"``); ``max_gap_s``: no pose
    across a longer gap, s (``inf``: none); ``gp_noise``: the GP given the white sources
    (``"white"``) or every source (``"all"``, the paper); ``motion_prior``: ``Qc`` scaled per class
    of motion (``"classes"``) or one per track (``"constant"``, the paper); ``outlier_windows``:
    the measurements of distance-rejected windows left out of the GP fits (``"remove"``) or kept
    (``"keep"``, the paper); ``prior``: ``"wnoa"`` (the paper's), ``"wnoj"`` or ``"select"``;
    ``correlated_noise``: time-correlated static noise carried by inflating the white covariance
    (``"inflate"``) or not (``"ignore"``, the paper; docs/noise-model.md).
    """

    rate_hz: float = 5.0
    qc: float | QcMethod = DEFAULT_QC
    max_gap_s: float = DEFAULT_MAX_GAP_S
    gp_noise: GpNoise = "white"
    motion_prior: MotionPrior = "classes"
    outlier_windows: OutlierWindows = "remove"
    prior: MotionModel = DEFAULT_PRIOR
    correlated_noise: CorrelatedNoise = "ignore"

    def __post_init__(self) -> None:
        if not (np.isfinite(self.rate_hz) and self.rate_hz > 0):
            raise InputError(f"Expected a finite rate_hz > 0 Hz, got {self.rate_hz!r}")
        if not self.max_gap_s > 0:  # infinity switches the limit off; nan is refused
            raise InputError(f"Expected max_gap_s > 0, got {self.max_gap_s!r}")
        if isinstance(self.qc, str) and self.qc not in QC_METHODS:
            raise InputError(
                f"Expected qc {', '.join(QC_METHODS)} or a number (m^2/s^3), got {self.qc!r}")
        if not isinstance(self.qc, str) and not (np.isfinite(self.qc) and self.qc > 0):
            raise InputError(f"Expected qc > 0 m^2/s^3, got {self.qc!r}")
        one_of("gp_noise", self.gp_noise, GP_NOISE)
        one_of("motion_prior", self.motion_prior, MOTION_PRIORS)
        one_of("outlier_windows", self.outlier_windows, OUTLIER_WINDOWS)
        one_of("prior", self.prior, PRIOR_CHOICES)
        one_of("correlated_noise", self.correlated_noise, CORRELATED_NOISE)
