"""Continuous-time prism tracks: exact GP interpolation with a white-noise-on-acceleration
(WNOA, the paper's) or white-noise-on-jerk (WNOJ) prior (see :mod:`rtsgt.interpolation.gp`).

Three lines from a track to positions with covariance at any times::

    from rtsgt.interpolation import fit_track
    gp = fit_track(track, fit_qc=True)            # PrismTrack or (t, xyz, cov); prior="wnoj"
    res = gp.query(times)                         # res.position (Q, 3), res.position_cov (Q, 3, 3)
"""

from rtsgt.interpolation.gp import (
    DEFAULT_MAX_GAP_S,
    PRIORS,
    QC_BOUNDS,
    GPQuery,
    GPTrack,
    QcFitInfo,
    as_qc,
    fit_qc,
    fit_track,
    log_marginal_likelihood,
    wnoa_phi,
    wnoa_q,
    wnoa_q_inv,
    wnoj_phi,
    wnoj_q,
    wnoj_q_inv,
)

__all__ = [
    "DEFAULT_MAX_GAP_S",
    "PRIORS",
    "QC_BOUNDS",
    "GPQuery",
    "GPTrack",
    "QcFitInfo",
    "as_qc",
    "fit_qc",
    "fit_track",
    "log_marginal_likelihood",
    "wnoa_phi",
    "wnoa_q",
    "wnoa_q_inv",
    "wnoj_phi",
    "wnoj_q",
    "wnoj_q_inv",
]
