"""Knots of the joint trajectory, their initial values and a first ``Qc``.

Knots at the query times and at the measurement times (times closer than ``merge_s`` share
one); initial poses and body velocities from another engine's poses: docs/joint.md#knots.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation, Slerp

from rtsgt.errors import InputError
from rtsgt.joint.prior import relative_log

#: Measurement times closer than this to a knot are predicted from it, s.
DEFAULT_MERGE_S = 1e-3


@dataclass(frozen=True)
class Knots:
    """``t`` (K,) s; ``of_measurement`` (M,) each measurement's knot and ``tau`` (M,) its time
    minus the knot's, s; ``of_query`` (Q,) each query time's knot (its time exactly)."""

    t: np.ndarray
    of_measurement: np.ndarray
    tau: np.ndarray
    of_query: np.ndarray


def build_knots(t_meas: np.ndarray, t_query: np.ndarray, merge_s: float = DEFAULT_MERGE_S
                ) -> Knots:
    """Knots at the sorted union of the times, a run of times each within ``merge_s`` of the
    previous one sharing a knot (at its query time if it has one, else its first time)."""
    t_meas = np.asarray(t_meas, dtype=float)
    t_query = np.asarray(t_query, dtype=float)
    if t_query.ndim != 1 or np.any(np.diff(t_query) <= merge_s):
        raise InputError(f"Expected query times increasing by more than {merge_s} s")
    t_all = np.concatenate([t_query, t_meas])
    is_query = np.concatenate([np.ones(t_query.size, bool), np.zeros(t_meas.size, bool)])
    order = np.lexsort((~is_query, t_all))  # by time, a query first among equal times
    ts = t_all[order]
    group = np.concatenate([[0], np.cumsum(np.diff(ts) > merge_s)])
    K = int(group[-1]) + 1
    first = np.searchsorted(group, np.arange(K))
    t_knot = ts[first].copy()
    q_sorted = is_query[order]
    t_knot[group[q_sorted]] = ts[q_sorted]  # a query time is its knot's time
    of_all = np.empty(t_all.size, dtype=int)
    of_all[order] = group
    of_query, of_meas = of_all[: t_query.size], of_all[t_query.size:]
    return Knots(t_knot, of_meas, t_meas - t_knot[of_meas], of_query)


def interpolate_poses(t_knot, t_pose, R_pose, p_pose):
    """Poses at ``t_knot`` (K,) from poses at ``t_pose`` (T,), ``R_pose`` (T, 3, 3),
    ``p_pose`` (T, 3): linear in position, slerp in rotation, held beyond the ends."""
    tc = np.clip(t_knot, t_pose[0], t_pose[-1])
    R = Slerp(t_pose, Rotation.from_matrix(R_pose))(tc).as_matrix()
    p = np.stack([np.interp(tc, t_pose, p_pose[:, i]) for i in range(3)], axis=1)
    return R, p


def body_velocities(t: np.ndarray, R: np.ndarray, p: np.ndarray) -> np.ndarray:
    """Body-centric velocities (K, 6) ``log(T_k^-1 T_k+1) / dt`` (the last repeats)."""
    if t.size < 2:
        return np.zeros((t.size, 6))
    w = relative_log(R, p) / np.diff(t)[:, None]
    return np.concatenate([w, w[-1:]])


def qc_from_prisms(qc_prisms: np.ndarray, p_body: np.ndarray) -> np.ndarray:
    """A diagonal body ``Qc`` (6,) from the per-prism GPs' ``Qc`` (P, 3, 3) (m^2/s^3, world
    frame): translation the prisms' mean (x and y their horizontal mean, z the vertical);
    each rotation the horizontal mean over ``r^2``, the prisms' mean squared distance from
    their centroid (all of a prism's acceleration taken as rotation: an upper bound)."""
    q = np.einsum("pii->pi", np.asarray(qc_prisms, dtype=float)).mean(axis=0)
    qh = 0.5 * (q[0] + q[1])
    p = np.asarray(p_body, dtype=float)
    r2 = float(np.mean(np.sum((p - p.mean(axis=0)) ** 2, axis=1)))
    return np.array([qh, qh, q[2], qh / r2, qh / r2, qh / r2])
