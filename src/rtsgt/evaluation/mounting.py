r"""Sensor mounting and clock offset of an estimate, fitted jointly with the world alignment.

A SLAM method estimates the pose of its own sensor, ``T_E_sensor(t)``, in its own world frame
``E`` and on its own clock; the ground truth is the pose of the body frame, ``T_W_body(tau)``,
in the world frame ``W``. Between them lie the world alignment ``A`` (:mod:`.align`), the
**mounting** ``T_body_sensor`` and a **clock offset** ``o``::

    T_W_body(t + o) = A  T_E_sensor(t)  T_body_sensor^-1

``T_body_sensor = (R_bs, l)`` maps sensor coordinates into body coordinates
(``p_body = R_bs p_sensor + l``, :mod:`rtsgt.geometry.transform`): it is the sensor's pose in
the body frame, and ``l`` is the lever arm from the body origin to the sensor origin, in the
body frame. ``o`` is added to the estimate's times (evo's ``--t_offset``). With
``A = (s, R_a, t_a)`` the body pose the estimate predicts at its pose ``k`` is

.. math::

    \hat R_k = R_a R_{e,k} R_{bs}^T, \qquad
    \hat p_k = s R_a p_{e,k} + t_a - \hat R_k l,

the lever arm metric (not scaled by ``s``). Its error against the ground truth at
``tau_k = t_k + o`` is the pose error of :func:`~rtsgt.evaluation.metrics.pose_error`,
``r_k = (p^_k - p_gt(tau_k), log(R^_k R_gt(tau_k)^T))`` (the first three rows alone for a
position-only ground truth).

Weighted least squares
----------------------
The parameters (the alignment, and those of ``R_bs``, ``l``, ``o`` that are asked for) minimise
``r^T C^-1 r`` with ``C`` the covariance of the stacked errors: ``blockdiag(S_k) + L L^T``,
``S_k`` the ground truth's (varying) covariance plus the estimate's own covariance mapped by
the model, ``L`` the factor of the errors the deployment shares when the ground truth gives it
(:mod:`rtsgt.shared`; Woodbury: every sum is over poses of small blocks). Gauss-Newton on the
manifold, with left perturbations:

- alignment: ``t_a += dt``, ``R_a <- exp(phi) R_a``, ``s <- s exp(ds)``, rotation and scale
  about the ground truth's weighted centroid ``c`` (``d p^ = dt - [p^ - c]x phi + ds (q - c)``,
  ``q = s R_a p_e + t_a``; ``d theta^ = phi``); ``4dof`` keeps ``phi_z`` only;
- mounting rotation ``R_bs <- exp(psi) R_bs`` (the left perturbation in the body frame):
  ``d p^ = -R^ [l]x psi``, ``d theta^ = -R^ psi``;
- lever arm: ``d p^ = -R^ dl``;
- clock: the ground truth moves by its velocity, ``p_gt(tau + delta) = p_gt + v delta``,
  ``R_gt(tau + delta) = exp(w delta) R_gt`` (``v``, ``w``: world-frame linear and angular
  velocity), so ``d r = -(v, w) delta``. The evaluation re-queries the ground truth at the new
  offset until the step is below :data:`CLOCK_TOLERANCE_S` (:func:`rtsgt.evaluation.evaluate`),
  so the fixed point is exact, not linearised.

Start
-----
Gauss-Newton needs a start within its basin; a mounting rotation of 174 deg is far from the
identity. Candidates, each completed by a linear least-squares step for the alignment's
translation and scale, the lever arm and the clock (linear once the rotations are fixed), and
the one with the lowest cost kept:

1. ``R_a`` from the positions (Umeyama / 4-DOF Kabsch of the estimate's positions onto the
   ground truth's, the lever arm neglected), then ``R_bs`` as the chordal mean of
   ``R_gt,k^T R_a R_e,k``;
2. hand-eye (Park and Martin 1994): for pairs of poses, the relative rotations
   ``A = R_gt,i^T R_gt,j`` and ``B = R_e,i^T R_e,j`` satisfy ``A = R_bs B R_bs^T``, so their
   rotation vectors satisfy ``log A = R_bs log B``, a Kabsch problem; then ``R_a`` as the
   chordal mean of ``R_gt,k R_bs R_e,k^T`` (about z only for ``4dof``).

The first needs a trajectory whose extent dwarfs the lever arm, the second rotations about two
axes; a ground robot turning about its vertical has the first, a hand-held camera the second.

Covariance and refusal
----------------------
With ``H`` the Gauss-Newton normal matrix at the solution (Woodbury with ``L``), the
parameters' covariance is

.. math::

    \Sigma = f \left[ H^{-1} T K T H^{-1} + Q Q^T \right], \qquad
    Q = H^{-1} B^T M^{-1}, \qquad T = \mathrm{diag}(\sqrt{\tau_j}),

where ``Q Q^T`` is the shared errors' part (``B = sum L_k^T S_k^-1 J_k``,
``M = I + sum L_k^T S_k^-1 L_k``; ``Q = 0`` without ``L``) and ``H^-1 K H^-1`` the varying
errors' part (``K = sum Y_k^T Y_k``, ``Y_k = S_k^-1/2 (J_k - L_k M^-1 B)``: ``K = H - (M^-1
B)^T (M^-1 B)``, summed as squares so that a parameter the shared errors dominate, such as
the clock against the stations' clock offsets, keeps a positive variance; ``K = H`` without
``L``). The varying errors of a ground truth are correlated between nearby poses (the GP's
smoothing): each parameter's variance is inflated by ``tau_j``, the integrated
autocorrelation time (:func:`~rtsgt.evaluation.metrics.integrated_autocorrelation_time`) of
its score, the series of each pose's share of the gradient ``s_k = Y_k^T nu_k`` (``nu_k``
the whitened varying residual): a slowly varying regressor (the velocity, for the clock)
keeps the residual's correlation, a quickly varying one averages it out. ``f = max(1, chi2 /
(n - p))`` is the residual's scale when it exceeds its expectation (errors of the estimate its
covariance does not carry: the sigmas then follow the residual, not only the ground truth's
covariance).

A parameter is refused, with the reason, when its estimate would cost the evaluation more
than giving it by hand (:func:`sigma_limits`, docs/evaluating.md#the-refusal-rule): 0.02 m
for a lever-arm component, 1 deg per axis for the mounting rotation (:data:`HAND_LIMIT`), and
for the clock the sigma whose effect at the ground truth's rms speeds (``sigma v``, ``sigma
w``) reaches those, at most the 1 s searched. A parameter the trajectory does not excite (a
lever arm from a straight drive: the normal matrix is singular, its sigma infinite) is
always refused: a number would mislead.

A drifting odometry
-------------------
An odometry's own errors (drift, noise) are not in ``C``: the absolute fit's chi2 / dof then
far exceeds 1 and its sigmas, scaled by it, follow the drift. Above
:data:`ODOMETRY_CHI2_RATIO` the fit's covariance gets the odometry's own error beside the
ground truth's (:mod:`.handeye`: random walks of its position and yaw with the distance
driven, white noise of its poses; the drift states eliminated by a banded factorisation, the
four levels estimated by REML), so that the drift no longer enters as information. A refusal there says whether the motion does not excite the
parameter (its sigma from the ground truth's covariance alone is too large) or the odometry's
own error dominates (docs/evaluating.md#a-drifting-odometry).

References
----------
F. C. Park, B. J. Martin, "Robot sensor calibration: solving AX = XB on the Euclidean group",
IEEE Trans. Robotics and Automation 10(5), 1994. S. Umeyama, IEEE TPAMI 13(4), 1991.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

from rtsgt.choices import JOINT_ALIGNMENTS  # the alignments the mounting is estimated with
from rtsgt.errors import ExcitationError, GeometryError, InputError
from rtsgt.evaluation.align import Alignment, align_yaw, umeyama
from rtsgt.evaluation.handeye import (
    CLOCK_SEARCH_S,
    ODOMETRY_COMPONENTS,
    DriftModel,
    drift_model,
    fit_levels,
    level_covariance,
    profile_normal,
    score_bias,
)
from rtsgt.evaluation.metrics import integrated_autocorrelation_time
from rtsgt.geometry.so3 import exp_so3, hat, log_so3, matrix_to_quat_xyzw

__all__ = [
    "CLOCK_TOLERANCE_S",
    "check_position_only",
    "HAND_LIMIT",
    "JOINT_ALIGNMENTS",
    "MAX_SIGMA",
    "MOUNTING_PARAMETERS",
    "MountingFit",
    "fit_mounting",
    "mounting_sensitivity",
    "parse_estimate",
    "prism_lever_arm",
    "sigma_limits",
]

#: What can be estimated: the mounting rotation, the lever arm (all three components, or its
#: x and y components in the body frame with z given: for a ground robot, whose vertical
#: component only its tilts excite), the clock offset.
MOUNTING_PARAMETERS = ("rotation", "lever", "lever-xy", "clock")

#: Shorthands of ``--estimate``.
ESTIMATE_ALIASES = {"mounting": ("rotation", "lever"), "all": ("rotation", "lever", "clock")}


#: What a mounting measured by hand costs the evaluation: the error of a careful measurement
#: with a tape (the lever arm: a position error, m) and a CAD model or protractor (the
#: rotation: a rotation error, rad, per axis). An estimate whose own error costs more than
#: this is refused (:func:`sigma_limits`; docs/evaluating.md#the-refusal-rule).
HAND_LIMIT = {"position": 0.02, "rotation": float(np.radians(1.0))}

#: Largest standard deviation of the mounting's parameters (their effect on the evaluated
#: pose is their error itself): :data:`HAND_LIMIT`. The clock's depends on the motion
#: (:func:`sigma_limits`).
MAX_SIGMA = {"rotation": HAND_LIMIT["rotation"], "lever": HAND_LIMIT["position"],
             "lever-xy": HAND_LIMIT["position"]}

#: Above this chi2 / dof of the absolute fit the estimate's own errors (an odometry's drift and
#: noise) are larger than the covariances it was weighted by: the mounting and the clock are
#: then fitted on the relative motion with a model of those errors (:mod:`.handeye`).
ODOMETRY_CHI2_RATIO = 2.0
#: Rounds of the odometry's levels and the fit at most (:func:`fit_mounting`).
ODOMETRY_ROUNDS = 5

#: The clock is re-associated until its step is below this, s (a micrometre at 1 m/s).
CLOCK_TOLERANCE_S = 1e-6

#: Names of the parameters of each group, in order (rotation: left perturbation of
#: ``R_body_sensor`` in the body frame, rad; lever arm: ``t_body_sensor``, m; clock, s).
PARAMETER_NAMES = {
    "rotation": ("rotation_x", "rotation_y", "rotation_z"),
    "lever": ("lever_x", "lever_y", "lever_z"),
    "lever-xy": ("lever_x", "lever_y"),
    "clock": ("clock",),
}

#: Relative size below which an eigenvalue of the scaled normal matrix is numerically zero.
_RCOND = 1e-13


def parse_estimate(value: str | Iterable[str] | None) -> tuple[str, ...]:
    """The parameters to estimate, in the order of :data:`MOUNTING_PARAMETERS`.

    ``value``: a comma-separated string or an iterable of names of
    :data:`MOUNTING_PARAMETERS` or :data:`ESTIMATE_ALIASES`; None or empty: nothing.

    Raises
    ------
    InputError
        An unknown name.
    """
    if value is None:
        return ()
    items = value.split(",") if isinstance(value, str) else list(value)
    out: set[str] = set()
    for raw in items:
        name = str(raw).strip().lower()
        if not name:
            continue
        if name in ESTIMATE_ALIASES:
            out.update(ESTIMATE_ALIASES[name])
        elif name in MOUNTING_PARAMETERS:
            out.add(name)
        else:
            known = ", ".join(MOUNTING_PARAMETERS + tuple(ESTIMATE_ALIASES))
            raise InputError(f"Expected parameters to estimate among {known}, got {name!r}")
    if "lever" in out:
        out.discard("lever-xy")
    return tuple(p for p in MOUNTING_PARAMETERS if p in out)


def _lever_group(estimate: tuple[str, ...]) -> str | None:
    """``lever``, ``lever-xy`` or None."""
    return next((g for g in ("lever", "lever-xy") if g in estimate), None)


def _lever_axes(estimate: tuple[str, ...]) -> list[int]:
    """The components of the lever arm estimated."""
    g = _lever_group(estimate)
    return [] if g is None else [0, 1, 2][:len(PARAMETER_NAMES[g])]


def sigma_limits(estimate: Iterable[str], velocity: ArrayLike | None = None,
                 angular_velocity: ArrayLike | None = None) -> dict[str, tuple[float, str]]:
    """The largest standard deviation of each estimated group, and its reason in words.

    The rotation and the lever arm: :data:`MAX_SIGMA`. The clock: an error ``delta`` moves the
    ground truth by ``v delta`` and ``w delta``; the limit is where that effect, at the ground
    truth's rms speeds over the associated poses (``velocity`` (N, 3) m/s, ``angular_velocity``
    (N, 3) rad/s or None for positions), reaches :data:`HAND_LIMIT`, and at most
    :data:`~rtsgt.evaluation.handeye.CLOCK_SEARCH_S` (the range searched: a wider sigma says
    nothing of the offset). docs/evaluating.md#the-refusal-rule.
    """
    out = {}
    for g in parse_estimate(estimate):
        if g == "rotation":
            out[g] = (MAX_SIGMA[g], f"{np.degrees(MAX_SIGMA[g]):g} deg of a measurement by hand")
        elif g in ("lever", "lever-xy"):
            out[g] = (MAX_SIGMA[g], f"{MAX_SIGMA[g]:g} m of a measurement by hand")
        else:
            out[g] = _clock_limit(velocity, angular_velocity)
    return out


def _clock_limit(velocity: ArrayLike | None,
                 angular_velocity: ArrayLike | None) -> tuple[float, str]:
    """:func:`sigma_limits` of the clock."""
    cands = [(CLOCK_SEARCH_S, f"{CLOCK_SEARCH_S:g} s searched")]
    for rates, hand, unit, what in ((velocity, "position", "m/s", "a lever arm"),
                                    (angular_velocity, "rotation", "deg/s", "a rotation")):
        if rates is None:
            continue
        rms = float(np.sqrt(np.mean(np.sum(np.square(rates), axis=-1))))
        lim = HAND_LIMIT[hand] / rms if rms > 0 else np.inf
        size = (f"{HAND_LIMIT[hand]:g} m" if hand == "position"
                else f"{np.degrees(HAND_LIMIT[hand]):g} deg")
        rate = rms if hand == "position" else np.degrees(rms)
        cands.append((lim, f"{lim:.3g} s, where its effect at the ground truth's rms speed of "
                           f"{rate:.3g} {unit} reaches the {size} of {what} measured by hand"))
    return min(cands, key=lambda c: c[0])


@dataclass(frozen=True)
class MountingFit:
    """The mounting ``T_body_sensor`` and the clock offset, given or estimated.

    Attributes
    ----------
    rotation : ndarray, shape (3, 3)
        ``R_body_sensor``.
    lever : ndarray, shape (3,)
        ``t_body_sensor``: the sensor origin in the body frame, m.
    clock_offset : float
        Added to the estimate's times, s.
    estimated : tuple of str
        The groups of :data:`MOUNTING_PARAMETERS` that were estimated.
    names : tuple of str
        The estimated parameters (:data:`PARAMETER_NAMES`), in the order of ``covariance``.
    covariance : ndarray, shape (p, p)
        Their covariance: rotation as the left perturbation of ``R_body_sensor`` in the body
        frame (rad), lever arm (m), clock (s).
    alignment : Alignment
        The world alignment fitted jointly (weighted by the ground truth's covariance).
    chi2 : float
        ``r^T C^-1 r`` at the solution.
    dof : int
        Number of residuals less the number of parameters (alignment included).
    time_correlation : float
        The largest ``tau_j`` of the estimated parameters (module docstring): the factor by
        which the correlation of the ground truth's errors between poses inflates a variance.
    scale_factor : float
        ``f`` of the covariance.
    iterations : int
        Gauss-Newton iterations (of the last clock association).
    n_used : int
        Poses the fit used.
    start : str
        The start Gauss-Newton converged from (``positions``, ``hand-eye``, ``rotations``,
        ``given``).
    model : str
        ``absolute`` (weighted by the covariances given) or ``odometry`` (with the
        odometry's own drift and noise estimated beside them, :mod:`.handeye`).
    odometry : dict or None
        With ``odometry``: its error levels (standard deviations of
        :data:`~rtsgt.evaluation.handeye.ODOMETRY_COMPONENTS`: m, rad, m / sqrt(m),
        rad / sqrt(m)).
    limits : dict or None
        The largest standard deviation each estimated group was accepted with
        (:func:`sigma_limits`: rad, m, s).
    """

    rotation: np.ndarray
    lever: np.ndarray
    clock_offset: float
    estimated: tuple[str, ...] = ()
    names: tuple[str, ...] = ()
    covariance: np.ndarray | None = None
    alignment: Alignment | None = None
    chi2: float = float("nan")
    dof: int = 0
    time_correlation: float = 1.0
    scale_factor: float = 1.0
    iterations: int = 0
    n_used: int = 0
    start: str = "given"
    model: str = "absolute"
    odometry: dict | None = None
    limits: dict | None = None

    @classmethod
    def given(cls, rotation: ArrayLike | None = None, lever: ArrayLike | None = None,
              clock_offset: float = 0.0) -> MountingFit:
        """A mounting given, not estimated (identity and 0 by default)."""
        R = np.eye(3) if rotation is None else np.asarray(rotation, dtype=float)
        t = np.zeros(3) if lever is None else np.asarray(lever, dtype=float)
        return cls(R, t, float(clock_offset))

    @property
    def sigma(self) -> dict[str, float]:
        """Standard deviation of every estimated parameter, by name."""
        if self.covariance is None:
            return {}
        s = np.sqrt(np.clip(np.diagonal(self.covariance), 0.0, None))
        return {n: float(v) for n, v in zip(self.names, s, strict=True)}

    def group_sigma(self, group: str) -> np.ndarray | None:
        """Standard deviations of ``rotation`` (3), ``lever`` (3; NaN for a component given)
        or ``clock`` (1); None when nothing of the group was estimated."""
        s = self.sigma
        if group == "lever":
            names = PARAMETER_NAMES["lever"]
            if not any(n in s for n in names):
                return None
            return np.array([s.get(n, np.nan) for n in names])
        if group not in self.estimated:
            return None
        return np.array([s[n] for n in PARAMETER_NAMES[group]])

    def as_matrix(self) -> np.ndarray:
        """``T_body_sensor`` as a 4x4 matrix."""
        T = np.eye(4)
        T[:3, :3] = self.rotation
        T[:3, 3] = self.lever
        return T

    @property
    def rotation_vector(self) -> np.ndarray:
        """``log(R_body_sensor)``, rad."""
        return log_so3(self.rotation)

    def to_prism_dict(self) -> dict:
        """JSON-ready, against a ground truth of positions: the tracked point's lever arm in
        the sensor frame (:func:`prism_lever_arm`) and the clock, their sigmas (null where
        given) and the fit."""
        lever, cov = prism_lever_arm(self)
        ls = self.group_sigma("lever")
        cs = self.group_sigma("clock")
        out = self.to_dict()
        for key in ("T_body_sensor", "quat_xyzw", "rotation_angle_deg", "rotation_axis",
                    "rotation_sigma_deg", "lever_m", "lever_sigma_m"):
            out.pop(key)
        out["given"] = [g for g in out["given"] if g != "rotation"]
        out.update({
            "lever_arm_m": lever.tolist(), "lever_arm_frame": "sensor (estimate)",
            "lever_arm_sigma_m": None if ls is None else [
                None if not np.isfinite(v) else float(v) for v in ls],
            "lever_arm_cov_m2": cov.tolist(),
            "clock_sigma_s": None if cs is None else float(cs[0])})
        if "covariance" in out:  # the lever arm's sign flipped: l = -t_body_sensor
            sign = np.array([-1.0 if n.startswith("lever_") else 1.0 for n in self.names])
            out["covariance"] = (sign[:, None] * self.covariance * sign[None, :]).tolist()
        return out

    def to_dict(self) -> dict:
        """JSON-ready: the values, their sigmas (null where given) and the fit."""
        rv = self.rotation_vector
        angle = float(np.linalg.norm(rv))
        rs, ls, cs = (self.group_sigma(g) for g in ("rotation", "lever", "clock"))
        given = [g for g in ("rotation", "lever", "clock") if self.group_sigma(g) is None]
        if "lever-xy" in self.estimated:
            given.append("lever_z")
        out = {
            "estimated": list(self.estimated),
            "given": given,
            "T_body_sensor": self.as_matrix().tolist(),
            "quat_xyzw": matrix_to_quat_xyzw(self.rotation).tolist(),
            "rotation_angle_deg": float(np.degrees(angle)),
            "rotation_axis": (rv / angle).tolist() if angle > 0 else [0.0, 0.0, 1.0],
            "rotation_sigma_deg": None if rs is None else np.degrees(rs).tolist(),
            "lever_m": self.lever.tolist(),
            "lever_sigma_m": None if ls is None else [
                None if not np.isfinite(v) else float(v) for v in ls],
            "clock_offset_s": float(self.clock_offset),
            "clock_sigma_s": None if cs is None else float(cs[0]),
        }
        if self.covariance is not None:
            out["names"] = list(self.names)
            out["covariance"] = self.covariance.tolist()
            out["fit"] = {
                "n_used": int(self.n_used),
                "chi2": float(self.chi2),
                "dof": int(self.dof),
                "time_correlation": float(self.time_correlation),
                "scale_factor": float(self.scale_factor),
                "iterations": int(self.iterations),
                "start": self.start,
                "model": self.model,
                "odometry": self.odometry,
                "alignment": None if self.alignment is None else self.alignment.to_dict(),
                "max_sigma": {g: (self.limits or MAX_SIGMA)[g] for g in self.estimated},
            }
        return out


# --------------------------------------------------------------------------------------------
# the model
# --------------------------------------------------------------------------------------------


@dataclass
class _State:
    """Alignment ``(s, R_a, t_a)``, mounting ``(R_bs, l)`` and the clock step ``delta``."""

    s: float
    Ra: np.ndarray
    ta: np.ndarray
    Rbs: np.ndarray
    lever: np.ndarray
    delta: float

    def copy(self) -> _State:
        return _State(self.s, self.Ra.copy(), self.ta.copy(), self.Rbs.copy(),
                      self.lever.copy(), self.delta)


@dataclass(frozen=True)
class _Data:
    pg: np.ndarray  # (N, 3)
    Rg: np.ndarray | None  # (N, 3, 3)
    S: np.ndarray  # (N, d, d) ground-truth (varying) covariance
    pe: np.ndarray
    Re: np.ndarray
    cov_e: np.ndarray | None  # (N, 6, 6)
    shared: np.ndarray | None  # (N, d, k)
    v: np.ndarray | None  # (N, 3)
    w: np.ndarray | None  # (N, 3)
    c: np.ndarray  # pivot (3,)
    d: int


def _n_align(align: str) -> int:
    return {"none": 0, "se3": 6, "sim3": 7, "4dof": 4}[align]


def _layout(align: str, estimate: tuple[str, ...]) -> dict[str, slice]:
    """Slices of the parameter vector: alignment, then the estimated groups."""
    out = {"align": slice(0, _n_align(align))}
    k = _n_align(align)
    for g in MOUNTING_PARAMETERS:
        if g in estimate:
            n = len(PARAMETER_NAMES[g])
            out[g] = slice(k, k + n)
            k += n
    out["all"] = slice(0, k)
    return out


def _predict(x: _State, D: _Data) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``q = s R_a p_e + t_a``, ``R^`` and ``p^`` of every pose."""
    q = x.s * D.pe @ x.Ra.T + x.ta
    Rh = x.Ra @ D.Re @ x.Rbs.T
    ph = q - Rh @ x.lever
    return q, Rh, ph


def _residual(x: _State, D: _Data) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Residuals (N, d), and ``q``, ``R^``, ``p^``."""
    q, Rh, ph = _predict(x, D)
    pg = D.pg if D.v is None else D.pg + x.delta * D.v
    rp = ph - pg
    if D.d == 3:
        return rp, q, Rh, ph
    Rg = D.Rg if D.w is None else exp_so3(x.delta * D.w) @ D.Rg
    rr = log_so3(Rh @ np.swapaxes(Rg, 1, 2))
    return np.concatenate([rp, rr], axis=1), q, Rh, ph


def _jacobian(x: _State, D: _Data, align: str, estimate: tuple[str, ...],
              q: np.ndarray, Rh: np.ndarray, ph: np.ndarray) -> np.ndarray:
    """``d r / d parameters``, shape (N, d, p), in the order of :func:`_layout`."""
    N = D.pe.shape[0]
    lay = _layout(align, estimate)
    J = np.zeros((N, 6, lay["all"].stop))
    a = lay["align"]
    if align != "none":
        cols = np.zeros((N, 6, 7))
        cols[:, :3, :3] = np.eye(3)
        cols[:, :3, 3:6] = -hat(ph - D.c)
        cols[:, 3:, 3:6] = np.eye(3)
        cols[:, :3, 6] = q - D.c
        keep = {"se3": [0, 1, 2, 3, 4, 5], "sim3": list(range(7)), "4dof": [0, 1, 2, 5]}[align]
        J[:, :, a] = cols[:, :, keep]
    if "rotation" in estimate:
        J[:, :3, lay["rotation"]] = -Rh @ hat(x.lever)
        J[:, 3:, lay["rotation"]] = -Rh
    lever = _lever_group(estimate)
    if lever is not None:
        J[:, :3, lay[lever]] = -Rh[:, :, _lever_axes(estimate)]
    if "clock" in estimate:
        J[:, :3, lay["clock"].start] = -D.v
        if D.w is not None:
            J[:, 3:, lay["clock"].start] = -D.w
    return J[:, :D.d]


def _covariance(x: _State, D: _Data, Rh: np.ndarray) -> np.ndarray:
    """``S_k``: the ground truth's covariance plus the estimate's, mapped by the model."""
    if D.cov_e is None:
        return D.S
    N = D.pe.shape[0]
    Je = np.zeros((N, 6, 6))
    Je[:, :3, :3] = x.s * x.Ra
    Je[:, :3, 3:] = x.Ra @ hat(np.einsum("nij,j->ni", D.Re @ x.Rbs.T, x.lever))
    Je[:, 3:, 3:] = x.Ra
    S_e = Je @ D.cov_e @ np.swapaxes(Je, 1, 2)
    return D.S + S_e[:, :D.d, :D.d]


@dataclass(frozen=True)
class _Normal:
    H: np.ndarray
    g: np.ndarray
    chi2: float
    Q0: np.ndarray | None  # M^-1 B: the shared parameters' response to the parameters
    K: np.ndarray  # J^T C^-1 blockdiag(S) C^-1 J: the varying part's information
    varying: np.ndarray  # whitened residual with the shared part removed (N, d)
    Y: np.ndarray  # whitened C^-1 J, pose by pose (N, d, p): the score is Y_k^T varying_k


class _Weights:
    """``C^-1`` of the stacked errors for fixed ``S_k`` and ``L`` (Cholesky factors of the
    ``S_k``, the whitened factor and the Woodbury matrix ``M = I + sum L^T S^-1 L``)."""

    def __init__(self, S: np.ndarray, L: np.ndarray | None):
        try:
            self.Lc = np.linalg.cholesky(S)
        except np.linalg.LinAlgError:
            raise InputError("Expected positive definite ground-truth covariances to estimate "
                             "the mounting") from None
        self.Lw = self.M = None
        if L is not None:
            self.Lw = np.linalg.solve(self.Lc, L)
            self.M = np.eye(L.shape[2]) + np.einsum("nia,nib->ab", self.Lw, self.Lw)

    def whiten(self, r: np.ndarray) -> np.ndarray:
        return np.linalg.solve(self.Lc, r[..., None])[..., 0]

    def chi2(self, r: np.ndarray) -> float:
        """``r^T C^-1 r``."""
        rw = self.whiten(r)
        out = float(np.sum(rw * rw))
        if self.Lw is None:
            return out
        bL = np.einsum("nia,ni->a", self.Lw, rw)
        return out - float(bL @ np.linalg.solve(self.M, bL))

    def normal(self, r: np.ndarray, J: np.ndarray) -> _Normal:
        """Normal matrix, gradient and cost of ``r^T C^-1 r`` (Woodbury with ``L``)."""
        Jw = np.linalg.solve(self.Lc, J)
        rw = self.whiten(r)
        H = np.einsum("nip,niq->pq", Jw, Jw)
        g = np.einsum("nip,ni->p", Jw, rw)
        chi2 = float(np.sum(rw * rw))
        if self.Lw is None:
            return _Normal(H, g, chi2, None, H, rw, Jw)
        Lw, M = self.Lw, self.M
        B = np.einsum("nia,nip->ap", Lw, Jw)
        bL = np.einsum("nia,ni->a", Lw, rw)
        Mi_B = np.linalg.solve(M, B)
        Mi_b = np.linalg.solve(M, bL)  # the shared parameters' estimate at this point
        varying = rw - np.einsum("nia,a->ni", Lw, Mi_b)
        Y = Jw - np.einsum("nia,ap->nip", Lw, Mi_B)  # whitened C^-1 J, pose by pose
        K = np.einsum("nip,niq->pq", Y, Y)
        return _Normal(H - B.T @ Mi_B, g - B.T @ Mi_b, chi2 - float(bL @ Mi_b), Mi_B, K,
                       varying, Y)


def _normal(r: np.ndarray, J: np.ndarray, S: np.ndarray, L: np.ndarray | None) -> _Normal:
    """Normal matrix, gradient and cost of ``r^T C^-1 r`` for ``C = blockdiag(S) + L L^T``."""
    return _Weights(S, L).normal(r, J)


#: Gauss-Newton stops when its step would lower ``chi2`` by less than this: the parameters
#: are then within a thousandth of their standard deviation of the minimum.
_CHI2_DECREASE = 1e-6


def _scaled_inverse(H: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Inverse of ``H`` through its diagonal scaling, and which parameters lie along a
    numerically singular direction (an eigenvalue of the scaled matrix below ``_RCOND`` of the
    largest, or a parameter without any effect): their variance is unbounded."""
    diag = np.diagonal(H)
    d = np.sqrt(np.clip(diag, 0.0, None))
    d = np.where(d > 0, d, 1.0)
    Hs = H / np.outer(d, d)
    w, V = np.linalg.eigh(0.5 * (Hs + Hs.T))
    top = max(float(w.max()), np.finfo(float).tiny)
    null = w <= _RCOND * top
    singular = (np.max(np.abs(V[:, null]), axis=1, initial=0.0) > 1e-6) | (diag <= 0)
    inv = (V[:, ~null] / w[~null]) @ V[:, ~null].T
    return inv / np.outer(d, d), singular


def _step(H: np.ndarray, g: np.ndarray) -> np.ndarray:
    """Gauss-Newton step ``-H^+ g`` (minimum norm along numerically singular directions)."""
    d = np.sqrt(np.clip(np.diagonal(H), 0.0, None))
    d = np.where(d > 0, d, 1.0)
    Hs = H / np.outer(d, d)
    w, V = np.linalg.eigh(0.5 * (Hs + Hs.T))
    top = max(float(w.max()), np.finfo(float).tiny)
    inv_w = np.where(w > 1e-10 * top, 1.0 / np.where(w > 0, w, 1.0), 0.0)
    return -((V * inv_w) @ V.T @ (g / d)) / d


def _update(x: _State, dx: np.ndarray, align: str, estimate: tuple[str, ...],
            c: np.ndarray) -> _State:
    lay = _layout(align, estimate)
    y = x.copy()
    if align != "none":
        a = np.zeros(7)
        a[{"se3": [0, 1, 2, 3, 4, 5], "sim3": list(range(7)), "4dof": [0, 1, 2, 5]}[align]] = \
            dx[lay["align"]]
        Rp = exp_so3(a[3:6])
        es = float(np.exp(a[6]))
        y.Ra = Rp @ x.Ra
        y.s = x.s * es
        y.ta = es * Rp @ (x.ta - c) + c + a[:3]
    if "rotation" in estimate:
        y.Rbs = exp_so3(dx[lay["rotation"]]) @ x.Rbs
    lever = _lever_group(estimate)
    if lever is not None:
        y.lever = x.lever.copy()
        y.lever[_lever_axes(estimate)] += dx[lay[lever]]
    if "clock" in estimate:
        y.delta = x.delta + float(dx[lay["clock"]][0])
    return y


# --------------------------------------------------------------------------------------------
# the start
# --------------------------------------------------------------------------------------------


def _project_so3(M: np.ndarray) -> np.ndarray:
    """The rotation nearest ``M`` in the Frobenius norm (chordal mean of a sum)."""
    U, _, Vt = np.linalg.svd(M)
    S = np.eye(3)
    S[2, 2] = np.sign(np.linalg.det(U @ Vt)) or 1.0
    return U @ S @ Vt


def _project_yaw(M: np.ndarray) -> np.ndarray:
    """The rotation about z nearest ``M``: ``argmax tr(R_z^T M)``."""
    psi = np.arctan2(M[1, 0] - M[0, 1], M[0, 0] + M[1, 1])
    c, s = np.cos(psi), np.sin(psi)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _mean_alignment_rotation(align: str, Rg: np.ndarray, Re: np.ndarray,
                             Rbs: np.ndarray) -> np.ndarray:
    """``R_a`` from the rotations: chordal mean of ``R_gt R_bs R_e^T`` (yaw only for 4dof)."""
    if align == "none":
        return np.eye(3)
    M = np.einsum("nij,jk,nlk->il", Rg, Rbs, Re)
    return _project_yaw(M) if align == "4dof" else _project_so3(M)


def _hand_eye(Rg: np.ndarray, Re: np.ndarray) -> np.ndarray | None:
    """``R_bs`` from relative rotations (module docstring), or None without rotation."""
    N = Rg.shape[0]
    strides = [m for m in 2 ** np.arange(20) if m < N]
    if not strides:
        return None
    i = np.concatenate([np.arange(N - m) for m in strides])
    j = np.concatenate([np.arange(m, N) for m in strides])
    alpha = log_so3(np.swapaxes(Rg[i], 1, 2) @ Rg[j])
    beta = log_so3(np.swapaxes(Re[i], 1, 2) @ Re[j])
    keep = (np.linalg.norm(alpha, axis=1) < 2.5) & (np.linalg.norm(beta, axis=1) < 2.5)
    if np.count_nonzero(keep) < 2:
        return None
    M = alpha[keep].T @ beta[keep]  # sum alpha beta^T, alpha = R_bs beta
    if np.linalg.svd(M, compute_uv=False)[0] <= 0:
        return None
    return _project_so3(M)


def _linear_start(x: _State, D: _Data, align: str, estimate: tuple[str, ...],
                  W: np.ndarray) -> _State:
    """Translation, scale, lever arm and clock by linear least squares on the positions,
    the rotations fixed."""
    N = D.pe.shape[0]
    Rh = x.Ra @ D.Re @ x.Rbs.T
    cols, names = [], []
    if align != "none":
        cols.append(np.broadcast_to(np.eye(3), (N, 3, 3)))
        names.append("t")
    if align == "sim3":
        cols.append((D.pe @ x.Ra.T)[:, :, None])
        names.append("s")
    axes = _lever_axes(estimate)
    if axes:
        cols.append(-Rh[:, :, axes])
        names.append("l")
    if "clock" in estimate:
        cols.append(-D.v[:, :, None])
        names.append("delta")
    rhs = D.pg.copy()
    if align != "sim3":
        rhs -= x.s * D.pe @ x.Ra.T
    if align == "none":
        rhs -= x.ta
    given = x.lever.copy()
    given[axes] = 0.0
    rhs += Rh @ given
    if not cols:
        return x
    A = np.concatenate(cols, axis=2)  # (N, 3, m)
    Lw = np.linalg.cholesky(W)  # W = S^-1 of the positions
    Aw = np.swapaxes(Lw, 1, 2) @ A
    bw = np.einsum("nji,nj->ni", Lw, rhs)
    sol = np.linalg.lstsq(Aw.reshape(-1, A.shape[2]), bw.reshape(-1), rcond=None)[0]
    y = x.copy()
    k = 0
    for n in names:
        if n == "t":
            y.ta = sol[k:k + 3]
            k += 3
        elif n == "s":
            y.s = float(sol[k]) if sol[k] > 0 else x.s
            k += 1
        elif n == "l":
            y.lever = x.lever.copy()
            y.lever[axes] = sol[k:k + len(axes)]
            k += len(axes)
        else:
            y.delta = float(sol[k])
            k += 1
    return y


def _starts(D: _Data, align: str, estimate: tuple[str, ...], Rbs0: np.ndarray,
            lever0: np.ndarray) -> list[tuple[str, _State]]:
    """Candidate rotations ``(R_a, R_bs)`` of the start (module docstring)."""
    out: list[tuple[str, np.ndarray, np.ndarray, float]] = []
    rot = "rotation" in estimate
    if align == "none":
        out.append(("positions", np.eye(3), np.zeros(3), 1.0))
    else:
        try:
            if align == "4dof":
                Ra, ta = align_yaw(D.pe, D.pg)
                s = 1.0
            else:
                Ra, ta, s = umeyama(D.pe, D.pg, with_scale=align == "sim3")
            out.append(("positions", Ra, ta, s))
        except GeometryError:
            pass
    starts = []
    for name, Ra, ta, s in out:
        Rbs = Rbs0
        if rot and D.Rg is not None:
            Rbs = _project_so3(np.einsum("nji,jk,nkl->il", D.Rg, Ra, D.Re))
        starts.append((name, _State(s, Ra, ta, Rbs, lever0.copy(), 0.0)))
    if D.Rg is not None:
        Rbs = _hand_eye(D.Rg, D.Re) if rot else None
        name = "hand-eye"
        if Rbs is None:  # no relative rotation: the given (or identity) mounting rotation
            Rbs, name = Rbs0, "rotations"
        Ra = _mean_alignment_rotation(align, D.Rg, D.Re, Rbs)
        s = starts[0][1].s if align == "sim3" and starts else 1.0
        starts.append((name, _State(s, Ra, np.zeros(3), Rbs, lever0.copy(), 0.0)))
    if not starts:
        raise GeometryError("Degenerate alignment: neither the positions nor the rotations "
                            "determine the alignment's rotation")
    return starts


# --------------------------------------------------------------------------------------------
# the fit
# --------------------------------------------------------------------------------------------


def _as_array(a: ArrayLike, shape: tuple, what: str) -> np.ndarray:
    x = np.asarray(a, dtype=float)
    if x.shape != shape:
        raise ValueError(f"Expected {what} of shape {shape}, got {x.shape}")
    if not np.all(np.isfinite(x)):
        raise ValueError(f"Expected finite {what}, got NaN or inf")
    return x


def check_position_only(estimate) -> None:
    """InputError when ``estimate`` asks for what a position-only ground truth cannot give:
    the mounting rotation."""
    if "rotation" in estimate:
        raise InputError("The mounting rotation cannot be estimated from a position-only "
                         "ground truth: it sees the sensor's rotation only through the lever "
                         "arm (the lever arm in the sensor frame and the clock can be "
                         "estimated); give it")


def fit_mounting(
    gt_position: ArrayLike,
    gt_rotation: ArrayLike | None,
    gt_cov: ArrayLike,
    est_position: ArrayLike,
    est_rotation: ArrayLike,
    *,
    estimate: Iterable[str] = ("rotation", "lever"),
    align: str = "se3",
    rotation: ArrayLike | None = None,
    lever: ArrayLike | None = None,
    clock_offset: float = 0.0,
    gt_velocity: ArrayLike | None = None,
    gt_angular_velocity: ArrayLike | None = None,
    gt_rate_cov: ArrayLike | None = None,
    est_cov: ArrayLike | None = None,
    shared: ArrayLike | None = None,
    max_iter: int = 50,
    odometry_levels: ArrayLike | None = None,
) -> MountingFit:
    r"""Estimate the mounting ``T_body_sensor`` and/or the clock offset with the alignment.

    Parameters
    ----------
    gt_position : array_like, shape (N, 3)
        Ground-truth body positions at ``t_k + clock_offset`` (world frame), m.
    gt_rotation : array_like, shape (N, 3, 3) or None
        Ground-truth ``R_world_body``; None for a position-only ground truth (then
        ``gt_cov`` is (N, 3, 3) and the mounting rotation cannot be estimated).
    gt_cov : array_like, shape (N, 6, 6) or (N, 3, 3)
        Ground-truth covariance (left perturbation, world frame); with ``shared``, its varying
        part only.
    est_position, est_rotation : array_like, shapes (N, 3), (N, 3, 3)
        The estimate's sensor poses ``T_E_sensor`` at ``t_k`` (its own frame).
    estimate : iterable of str
        Groups of :data:`MOUNTING_PARAMETERS` to estimate (at least one).
    align : str
        One of :data:`JOINT_ALIGNMENTS`.
    rotation, lever : array_like, optional
        ``R_body_sensor`` and ``t_body_sensor`` (identity, zero by default): the value used
        for a group that is not estimated.
    clock_offset : float
        The offset the ground truth was taken at, s (the estimate is relative to it).
    gt_velocity, gt_angular_velocity : array_like, shape (N, 3), optional
        The ground truth's world-frame linear (m/s) and angular (rad/s) velocity at the same
        times; needed to estimate the clock (the angular one with ``gt_rotation``).
    gt_rate_cov : array_like, shape (N, 6, 6) or (N, 3, 3), optional
        Covariance of the errors of ``(gt_velocity, gt_angular_velocity)`` (from the ground
        truth's own errors, :func:`~rtsgt.evaluation.associate.ground_truth_rates`). Noisy
        velocities feign information on the clock where the motion gives none (a constant
        velocity): their expected share, ``sum_k tr(S_k^-1 V_k)``, is removed from the clock's
        diagonal of the normal matrix for its covariance.
    est_cov : array_like, shape (N, 6, 6), optional
        The estimate's own covariance (left perturbation in its frame).
    shared : array_like, shape (N, d, k), optional
        Factor of the ground truth's errors shared by the poses (:mod:`rtsgt.shared`).
    max_iter : int
        Gauss-Newton iterations at most.
    odometry_levels : array_like, shape (4,), optional
        Where the odometry's levels (:data:`~rtsgt.evaluation.handeye.ODOMETRY_COMPONENTS`)
        start when its error is modelled (a previous fit's, at the last clock association);
        by default from the absolute fit's residual.

    Returns
    -------
    MountingFit

    Raises
    ------
    ExcitationError
        A parameter the trajectory does not excite, or that the odometry's own error hides
        (its sigma above :data:`MAX_SIGMA`; the message says which).
    InputError
        Nothing to estimate, an alignment that cannot be estimated with the mounting, the
        mounting rotation from a position-only ground truth, the clock without velocities,
        covariances that are not positive definite.
    GeometryError
        Neither the positions nor the rotations determine the alignment.
    """
    est = parse_estimate(estimate)
    if not est:
        raise InputError("Expected at least one parameter to estimate")
    if align not in JOINT_ALIGNMENTS:
        raise InputError(f"The mounting and the clock can be estimated with the alignments "
                         f"{', '.join(JOINT_ALIGNMENTS)}, not {align!r}")
    pg = np.asarray(gt_position, dtype=float)
    N = pg.shape[0] if pg.ndim == 2 else 0
    pg = _as_array(pg, (N, 3), "ground-truth positions")
    d = 3 if gt_rotation is None else 6
    Rg = None if gt_rotation is None else _as_array(gt_rotation, (N, 3, 3), "ground-truth rotations")
    S = _as_array(gt_cov, (N, d, d), "ground-truth covariances")
    pe = _as_array(est_position, (N, 3), "estimate positions")
    Re = _as_array(est_rotation, (N, 3, 3), "estimate rotations")
    if d == 3:
        check_position_only(est)
    v = w = None
    if "clock" in est:
        if gt_velocity is None or (d == 6 and gt_angular_velocity is None):
            raise InputError("Estimating the clock needs the ground truth's velocities")
        v = _as_array(gt_velocity, (N, 3), "ground-truth velocities")
        w = None if d == 3 else _as_array(gt_angular_velocity, (N, 3), "angular velocities")
    V = None
    if "clock" in est and gt_rate_cov is not None:
        V = np.asarray(gt_rate_cov, dtype=float)
        if V.ndim != 3 or V.shape[0] != N or V.shape[1] < d or V.shape[1] != V.shape[2]:
            raise ValueError(f"Expected rate covariances of shape ({N}, 6, 6), got {V.shape}")
        V = V[:, :d, :d]
    cov_e = None if est_cov is None else _as_array(est_cov, (N, 6, 6), "estimate covariances")
    L = None if shared is None else np.asarray(shared, dtype=float)
    if L is not None and (L.ndim != 3 or L.shape[:2] != (N, d)):
        raise ValueError(f"Expected a shared factor of shape ({N}, {d}, k), got {L.shape}")
    p_total = _layout(align, est)["all"].stop
    if N * d <= p_total:
        raise InputError(f"Estimating {', '.join(est)} with the alignment {align!r} needs more "
                         f"than {p_total / d:.0f} associated poses, got {N}")
    Rbs0 = np.eye(3) if rotation is None else _as_array(rotation, (3, 3), "mounting rotation")
    lever0 = np.zeros(3) if lever is None else _as_array(lever, (3,), "lever arm")
    W = np.linalg.inv(S[:, :3, :3])
    wt = np.trace(W, axis1=1, axis2=2)
    c = (wt @ pg) / wt.sum()
    D = _Data(pg, Rg, S, pe, Re, cov_e, L, v, w, c, d)

    best = None
    for name, x0 in _starts(D, align, est, Rbs0, lever0):
        x = _linear_start(x0, D, align, est, W)
        r, q, Rh, ph = _residual(x, D)
        nrm = _normal(r, _jacobian(x, D, align, est, q, Rh, ph), _covariance(x, D, Rh), L)
        if best is None or nrm.chi2 < best[2]:
            best = (name, x, nrm.chi2)
    start, x, _ = best
    x, nrm, Rh, iterations = _gauss_newton(x, D, align, est, max_iter)
    if nrm.chi2 > ODOMETRY_CHI2_RATIO * (N * d - p_total):
        return _odometry(x, D, align, est, clock_offset, start, max_iter, odometry_levels)
    if V is not None:  # the information the velocities' noise feigns (gt_rate_cov)
        k = _layout(align, est)["clock"].start
        feigned = float(np.einsum("nij,nji->", np.linalg.inv(_covariance(x, D, Rh)), V))
        H = nrm.H.copy()
        H[k, k] = max(H[k, k] - feigned, 0.0)
        nrm = dataclasses.replace(nrm, H=H)
    return _result(x, D, align, est, nrm, Rh, iterations, start, clock_offset)


def _gauss_newton(x: _State, D: _Data, align: str, est: tuple[str, ...], max_iter: int):
    """Gauss-Newton with a halving line search on ``chi2`` at fixed weights (the estimate's
    own covariance moves with the mounting: the weights are refreshed after each step)."""
    r, q, Rh, ph = _residual(x, D)
    W = _Weights(_covariance(x, D, Rh), D.shared)
    nrm = W.normal(r, _jacobian(x, D, align, est, q, Rh, ph))
    it = 0
    for it in range(1, max_iter + 1):  # noqa: B007 (the count is reported)
        dx = _step(nrm.H, nrm.g)
        decrease = -float(nrm.g @ dx)  # predicted drop of chi2
        if decrease < _CHI2_DECREASE:
            break
        lam = 1.0
        for _ in range(20):
            y = _update(x, lam * dx, align, est, D.c)
            if W.chi2(_residual(y, D)[0]) < nrm.chi2:
                break
            lam *= 0.5
        else:
            break  # no descent at machine precision: converged
        x = y
        r, q, Rh, ph = _residual(x, D)
        W = _Weights(_covariance(x, D, Rh), D.shared)
        nrm = W.normal(r, _jacobian(x, D, align, est, q, Rh, ph))
    return x, nrm, Rh, it


def _result(x: _State, D: _Data, align: str, est: tuple[str, ...], nrm: _Normal,
            Rh: np.ndarray, iterations: int, start: str, clock_offset: float) -> MountingFit:
    lay = _layout(align, est)
    N = D.pe.shape[0]
    n_res = N * D.d
    p = lay["all"].stop
    dof = n_res - p
    Hinv, singular = _scaled_inverse(nrm.H)
    score = np.einsum("nip,ni->np", nrm.Y, nrm.varying)  # each pose's share of the gradient
    taus = np.array([integrated_autocorrelation_time(score[:, j]) for j in range(p)])
    root = np.sqrt(taus)
    f = max(1.0, nrm.chi2 / dof)
    varying = Hinv @ (root[:, None] * nrm.K * root[None, :]) @ Hinv
    if nrm.Q0 is None:
        cov = f * varying
    else:  # the varying part as a sandwich of a sum of squares: no cancellation
        Q = Hinv @ nrm.Q0.T
        cov = f * (varying + Q @ Q.T)
    tau = float(np.max(taus[np.r_[tuple(np.arange(p)[lay[g]] for g in est)]]))
    idx = np.r_[tuple(np.arange(p)[lay[g]] for g in est)]
    names = tuple(n for g in est for n in PARAMETER_NAMES[g])
    C = cov[np.ix_(idx, idx)]
    C = 0.5 * (C + C.T)
    sig = np.where(singular[idx], np.inf, np.sqrt(np.clip(np.diagonal(C), 0.0, None)))
    limits = sigma_limits(est, D.v, D.w)
    for g in est:
        gs = sig[[names.index(n) for n in PARAMETER_NAMES[g]]]
        bad = ~(gs <= limits[g][0])
        if np.any(bad):
            raise ExcitationError(_refusal(g, gs, bad, limits[g][1]))
    a = Alignment(align, x.Ra, x.ta, x.s, N, True)
    return MountingFit(
        rotation=x.Rbs, lever=x.lever, clock_offset=float(clock_offset + x.delta),
        estimated=est, names=names, covariance=C, alignment=a, chi2=nrm.chi2, dof=dof,
        time_correlation=tau, scale_factor=f, iterations=iterations, n_used=N, start=start,
        limits={g: v[0] for g, v in limits.items()})


def _odometry_start(x: _State, D: _Data) -> np.ndarray:
    """The start levels: white noise from the absolute residual, a small drift."""
    r = _residual(x, D)[0]
    white = np.sqrt(np.mean(r * r, axis=0))
    return np.array([white[:3].mean(), white[3:].mean() if D.d == 6 else 1e-2, 1e-3, 1e-4])


def _odometry(x: _State, D: _Data, align: str, est: tuple[str, ...], clock_offset: float,
              start: str, max_iter: int, levels: ArrayLike | None = None) -> MountingFit:
    """The mounting and the clock with the odometry's own error (:mod:`.handeye`): its levels
    (REML, from ``levels`` when given) and the fit alternated until the levels settle."""
    levels = _odometry_start(x, D) if levels is None else np.asarray(levels, dtype=float)
    for _ in range(ODOMETRY_ROUNDS):
        r, q, Rh, _ = _residual(x, D)
        S = _covariance(x, D, Rh)
        model = drift_model(S, Rh, x.lever, q, x.s)
        J = _jacobian(x, D, align, est, q, Rh, _predict(x, D)[2])
        new = fit_levels(model, r, J, levels, D.shared)
        settled = np.all(np.abs(np.log(new / levels)) < 0.03)
        levels = new
        x, H, chi2, iterations = _odometry_gauss_newton(x, D, align, est, levels, S, max_iter)
        if settled:
            break
    return _odometry_result(x, D, align, est, levels, H, chi2, S, iterations, start,
                            clock_offset)


def _regressor_noise(x: _State, D: _Data, align: str, est: tuple[str, ...],
                     model: DriftModel, ph: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """How the Jacobian of a position-only fit moves with the odometry's errors (the ``G``,
    ``Gs`` of :func:`~rtsgt.evaluation.handeye.score_bias`): the lever arm's columns
    ``-R^ e_j`` turn with the rotation errors (white and yaw drift), the alignment's rotation
    ``[e_i]x (p^ - c)`` and scale ``q - c`` columns move with the predicted positions."""
    lay = _layout(align, est)
    N, P = ph.shape[0], lay["all"].stop
    G = np.zeros((N, 2, 3, 3, P))
    Gs = np.zeros((N, 3, 4, P))
    if align != "none":
        keep = {"se3": [0, 1, 2, 3, 4, 5], "sim3": list(range(7)), "4dof": [0, 1, 2, 5]}[align]
        for col, j in enumerate(keep):
            if 3 <= j < 6:  # [e_i]x times the position errors
                e = hat(np.eye(3)[j - 3])
                G[:, :, :, :, col] = e @ model.E
                Gs[:, :, :, col] = e @ model.H
            elif j == 6:
                G[:, 0, :, :, col] = model.E[:, 0]
                Gs[:, :, :3, col] = np.eye(3)
    lever = _lever_group(est)
    if lever is not None:
        _, Rh, _ = _predict(x, D)
        for col, j in zip(range(lay[lever].start, lay[lever].stop), _lever_axes(est),
                          strict=True):
            G[:, 1, :, :, col] = hat(Rh[:, :, j])
            Gs[:, :, 3, col] = np.cross(Rh[:, :, j], [0.0, 0.0, 1.0])  # the yaw's axis
    return G, Gs


def _odometry_gauss_newton(x: _State, D: _Data, align: str, est: tuple[str, ...],
                           levels: np.ndarray, S: np.ndarray, max_iter: int):
    """Gauss-Newton on ``r^T C^-1 r`` with the drift states eliminated, the levels fixed;
    with a position-only ground truth, on its gradient less the expectation the noisy
    Jacobian gives it (the corrected score: the lever arm is otherwise shrunk)."""
    it = 0
    for it in range(1, max_iter + 1):  # noqa: B007 (the count is reported)
        r, q, Rh, ph = _residual(x, D)
        model = drift_model(S, Rh, x.lever, q, x.s)
        H, g, chi2, _ = profile_normal(model, levels, r, _jacobian(x, D, align, est, q, Rh, ph),
                                       D.shared)
        bias = (score_bias(model, levels, *_regressor_noise(x, D, align, est, model, ph),
                           D.shared) if D.d == 3 else np.zeros_like(g))
        dx = _step(H, g - bias)
        if -float((g - bias) @ dx) < _CHI2_DECREASE:
            break
        lam = 1.0
        for _ in range(20):
            y = _update(x, lam * dx, align, est, D.c)
            chi2_y = profile_normal(model, levels, _residual(y, D)[0], None, D.shared)[2]
            if chi2_y - 2.0 * lam * float(bias @ dx) < chi2:
                break
            lam *= 0.5
        else:
            break
        x = y
    return x, H, chi2, it


def _level_share(x: _State, D: _Data, align: str, est: tuple[str, ...], levels: np.ndarray,
                 S: np.ndarray, H: np.ndarray, r: np.ndarray, q: np.ndarray, Rh: np.ndarray,
                 ph: np.ndarray) -> np.ndarray:
    """The parameters' covariance (P, P) from the levels' own error (Kackar and Harville
    1984), for a position-only ground truth, where the corrected score depends much on them
    (its expectation grows with the rotation noise's variance): ``K Cov(log levels) K^T``,
    ``K = H^-1 d(gradient - bias) / d log levels`` at the solution."""
    P = H.shape[0]
    if D.d != 3:
        return np.zeros((P, P))
    model = drift_model(S, Rh, x.lever, q, x.s)
    J = _jacobian(x, D, align, est, q, Rh, ph)
    G, Gs = _regressor_noise(x, D, align, est, model, ph)
    h = 0.05
    dz = h * np.eye(4)

    def score(lev):
        return (profile_normal(model, lev, r, J, D.shared)[1]
                - score_bias(model, lev, G, Gs, D.shared))

    dF = np.stack([score(levels * np.exp(e)) - score(levels * np.exp(-e)) for e in dz],
                  axis=1) / (2 * h)
    K = _scaled_inverse(H)[0] @ dF
    return K @ level_covariance(model, r, J, levels, D.shared) @ K.T


def _odometry_result(x: _State, D: _Data, align: str, est: tuple[str, ...],
                     levels: np.ndarray, H: np.ndarray, chi2: float, S: np.ndarray,
                     iterations: int, start: str, clock_offset: float) -> MountingFit:
    lay = _layout(align, est)
    N = D.pe.shape[0]
    p = lay["all"].stop
    dof = D.d * N - p - len(levels)
    f = max(1.0, chi2 / dof)
    Hinv, singular = _scaled_inverse(H)
    r, q, Rh, ph = _residual(x, D)
    score = profile_normal(drift_model(S, Rh, x.lever, q, x.s), levels, r,
                           _jacobian(x, D, align, est, q, Rh, ph), D.shared, score=True)[4]
    # the ground truth's varying errors are correlated between nearby poses (module
    # docstring): each variance inflated by its score's integrated autocorrelation time
    root = np.sqrt([integrated_autocorrelation_time(score[:, j]) for j in range(p)])
    Hinv = root[:, None] * Hinv * root[None, :] + _level_share(x, D, align, est, levels, S,
                                                                 H, r, q, Rh, ph)
    # what the motion excites: the Jacobian along the ground truth's motion (the estimate's
    # noisy rotations would feign a turn), weighted by the ground truth's covariance alone
    motion = (Rh, ph) if D.Rg is None else (D.Rg, D.pg)
    H_gt = _Weights(S, D.shared).normal(r, _jacobian(x, D, align, est, q, *motion)).H
    Hinv_gt, singular_gt = _scaled_inverse(H_gt)
    idx = np.r_[tuple(np.arange(p)[lay[g]] for g in est)]
    names = tuple(n for g in est for n in PARAMETER_NAMES[g])
    C = f * Hinv[np.ix_(idx, idx)]
    C = 0.5 * (C + C.T)
    sig = np.where(singular[idx], np.inf, np.sqrt(np.clip(np.diagonal(C), 0.0, None)))
    sig_gt = np.where(singular_gt[idx], np.inf,
                      np.sqrt(np.clip(np.diagonal(Hinv_gt)[idx], 0.0, None)))
    sig = np.where(singular_gt[idx], np.inf, sig)
    odometry = {c: float(v) for c, v in zip(ODOMETRY_COMPONENTS, levels, strict=True)}
    limits = sigma_limits(est, D.v, D.w)
    for g in est:
        k = [names.index(n) for n in PARAMETER_NAMES[g]]
        lim, why = limits[g]
        bad = ~(sig[k] <= lim)
        if np.any(bad):
            hidden = bool(np.all(sig_gt[k][bad] <= lim))
            raise ExcitationError(_refusal(g, sig[k], bad, why, odometry if hidden else None))
    return MountingFit(
        rotation=x.Rbs, lever=x.lever, clock_offset=float(clock_offset + x.delta),
        estimated=est, names=names, covariance=C, alignment=Alignment(align, x.Ra, x.ta, x.s, N,
                                                                      True),
        chi2=chi2, dof=dof, time_correlation=float(np.max(root[idx]) ** 2), scale_factor=f,
        iterations=iterations,
        n_used=N, start=start, model="odometry", odometry=odometry,
        limits={g: v[0] for g, v in limits.items()})


def _odometry_text(levels: dict) -> str:
    """The odometry's error levels in words."""
    return (f"white noise {100 * levels['white_position']:.2g} cm and "
            f"{np.degrees(levels['white_rotation']):.2g} deg per pose, drift "
            f"{100 * levels['drift_position']:.2g} cm and "
            f"{np.degrees(levels['drift_yaw']):.2g} deg (yaw) per sqrt(m)")


def _refusal(group: str, sigma: np.ndarray, bad: np.ndarray, limit: str,
             odometry: dict | None = None) -> str:
    """The one-line reason of a refusal; ``limit``: the limit in words (:func:`sigma_limits`)."""
    k = int(np.argmax(np.where(bad, np.nan_to_num(sigma, nan=np.inf), -1.0)))
    what = {"rotation": "the mounting rotation", "lever": "the lever arm",
            "lever-xy": "the lever arm", "clock": "the clock offset"}[group]
    if group == "clock":
        part, val = "", _fmt(sigma[k], "s")
    elif group in ("lever", "lever-xy"):
        part = f" of its {'xyz'[k]} component (body frame)"
        val = _fmt(sigma[k], "m")
    else:
        part = f" about the body {'xyz'[k]} axis"
        val = _fmt(np.degrees(sigma[k]), "deg")
    lim = limit
    if odometry is not None:
        return (f"cannot estimate {what}: the odometry's own error ({_odometry_text(odometry)})"
                f" dominates what the motion excites (its standard deviation{part} would be "
                f"{val}, above the {lim}); give it instead, or "
                f"record a longer trajectory that "
                + {"rotation": "rotates about more axes",
                   "lever": "turns and tilts more (or estimate lever-xy)",
                   "lever-xy": "turns more",
                   "clock": "accelerates and turns more"}[group])
    return (f"cannot estimate {what}: the trajectory does not excite it (its standard "
            f"deviation{part} would be {val}, above the {lim}); "
            f"give it instead, or record a trajectory that "
            + {"rotation": "rotates about more axes",
               "lever": "turns (and tilts, for a vertical component; or estimate lever-xy)",
               "lever-xy": "turns",
               "clock": "accelerates or turns"}[group])


def _fmt(value: float, unit: str) -> str:
    if not np.isfinite(value):
        return "unbounded (the normal matrix is singular along it)"
    return f"{value:.3g} {unit}"


def prism_lever_arm(fit: MountingFit) -> tuple[np.ndarray, np.ndarray]:
    """The lever arm of a tracked point in the sensor frame, ``l`` (3,) m, and its covariance
    (3, 3) m^2 (zero for a component given), from a fit against a ground truth of positions:
    its body frame is the point's with the sensor's axes (``R_bs = I``), so ``l = -t_body_sensor``
    (docs/evaluating.md#position-only-ground-truth-one-tracked-prism)."""
    cov = np.zeros((3, 3))
    idx = [i for i, n in enumerate(fit.names) if n.startswith("lever_")]
    axes = ["xyz".index(fit.names[i][-1]) for i in idx]
    if fit.covariance is not None and idx:
        cov[np.ix_(axes, axes)] = fit.covariance[np.ix_(idx, idx)]
    return -np.asarray(fit.lever, dtype=float), cov


def mounting_sensitivity(fit: MountingFit, R_hat: ArrayLike, velocity: ArrayLike | None = None,
                         angular_velocity: ArrayLike | None = None, d: int = 6) -> np.ndarray:
    """``d e_k / d (estimated parameters)``, shape (N, d, p): how the pose errors move with the
    estimated mounting and clock (the columns of :func:`fit_mounting`'s Jacobian), for the
    split test to project out what the estimation absorbs.

    Parameters
    ----------
    fit : MountingFit
    R_hat : array_like, shape (N, 3, 3)
        The estimate's body rotations in the world frame.
    velocity, angular_velocity : array_like, shape (N, 3), optional
        The ground truth's velocities (needed when the clock was estimated).
    d : int
        6 (poses) or 3 (positions).
    """
    Rh = np.asarray(R_hat, dtype=float)
    N = Rh.shape[0]
    cols = []
    for g in fit.estimated:
        if g == "rotation":
            blk = np.zeros((N, 6, 3))
            blk[:, :3] = -Rh @ hat(fit.lever)
            blk[:, 3:] = -Rh
        elif g in ("lever", "lever-xy"):
            blk = np.zeros((N, 6, 3))
            blk[:, :3] = -Rh
            blk = blk[:, :, _lever_axes(fit.estimated)]
        else:
            if velocity is None or angular_velocity is None:
                raise ValueError("Expected the ground truth's velocities for the clock")
            blk = np.zeros((N, 6, 1))
            blk[:, :3, 0] = -np.asarray(velocity, dtype=float)
            blk[:, 3:, 0] = -np.asarray(angular_velocity, dtype=float)
        cols.append(blk)
    return np.concatenate(cols, axis=2)[:, :d]
