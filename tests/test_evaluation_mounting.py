"""The sensor mounting and the clock offset estimated with the alignment (rtsgt.evaluation.
mounting): exact recovery, consistency pooled over simulated deployments, the refusal of what
a trajectory does not excite, the weighted least squares against its dense form, and the
mounting's effect on APE / RPE and on the NEES."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from rtsgt.errors import ExcitationError, InputError
from rtsgt.evaluation import EvaluationOptions, evaluate
from rtsgt.evaluation.metrics import pose_error
from rtsgt.evaluation.mounting import (
    MAX_SIGMA,
    MountingFit,
    _normal,
    fit_mounting,
    mounting_sensitivity,
    parse_estimate,
)
from rtsgt.geometry.so3 import exp_so3, log_so3, matrix_to_quat_xyzw
from rtsgt.geometry.transform import perturb
from rtsgt.types import PoseTrajectory
from test_evaluation_synth import T0

#: The mounting of the acceptance: a rotation of more than 90 deg (174 deg about an axis near
#: the vertical, as the lidar of issue 14), a lever arm of 0.5 m, a clock 30 ms late.
AXIS = np.array([0.05, -0.03, 1.0]) / np.linalg.norm([0.05, -0.03, 1.0])
R_BS = exp_so3(np.radians(174.0) * AXIS)
LEVER = 0.5 * np.array([0.6, -0.7, 0.3]) / np.linalg.norm([0.6, -0.7, 0.3])
CLOCK = 0.03


def truth(tau: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A smooth 3-D drive at any time (the loop of ``test_evaluation_synth.smooth_truth`` in
    closed form): positions (N, 3) m and rotations (N, 3, 3), yaw along the path."""
    s = np.asarray(tau, dtype=float) - T0
    p = np.c_[20 * np.sin(s / 30) + 0.3 * np.sin(s / 3),
              15 * np.sin(s / 20) * np.cos(s / 45), 0.5 * np.sin(s / 10)]
    v = np.c_[2 / 3 * np.cos(s / 30) + 0.1 * np.cos(s / 3),
              0.75 * np.cos(s / 20) * np.cos(s / 45) - 1 / 3 * np.sin(s / 20) * np.sin(s / 45),
              0.05 * np.cos(s / 10)]
    yaw = np.arctan2(v[:, 1], v[:, 0])
    R = Rotation.from_euler("ZYX", np.c_[yaw, 0.04 * np.cos(s / 5), 0.05 * np.sin(s / 4)])
    return p, R.as_matrix()


class NoisyGroundTruth:
    """A continuous ground truth: the truth perturbed by ``xi(tau) ~ N(0, P)`` at every time,
    ``xi`` deterministic and smooth in ``tau`` (a Gaussian kernel of 10 ms over white draws on
    a 10 ms grid, normalised to unit variance), so that poses 0.1 s apart are independent
    (correlation 2e-11) and a query repeated at the same time gives the same pose."""

    H = 0.01

    def __init__(self, rng: np.random.Generator, span: tuple[float, float], P: np.ndarray):
        self.t0 = span[0] - 1.0
        self.z = rng.normal(size=(int((span[1] - span[0] + 2.0) / self.H) + 12, 6))
        self.P = P
        self.chol = np.linalg.cholesky(P)

    def noise(self, tau: np.ndarray) -> np.ndarray:
        x = (tau - self.t0) / self.H
        j = np.floor(x).astype(int)[:, None] + np.arange(-4, 6)[None]
        k = np.exp(-0.5 * (x[:, None] - j) ** 2)
        k /= np.sqrt(np.sum(k * k, axis=1, keepdims=True))
        return np.einsum("nk,nkc->nc", k, self.z[j]) @ self.chol.T

    def __call__(self, tau: np.ndarray) -> PoseTrajectory:
        p, R = truth(tau)
        Rn, pn = perturb(R, p, self.noise(tau))
        return PoseTrajectory(tau, pn, matrix_to_quat_xyzw(Rn),
                              np.broadcast_to(self.P, (tau.size, 6, 6)).copy())


def sensor_estimate(t: np.ndarray, rng: np.random.Generator, *, clock: float = CLOCK,
                    R_bs: np.ndarray = R_BS, lever: np.ndarray = LEVER, scale: float = 1.0,
                    yaw_only: bool = False) -> PoseTrajectory:
    """The exact pose of a sensor mounted by ``T_body_sensor = (R_bs, lever)``, stamped
    ``clock`` late (its pose at stamp t is the truth at t + clock), in a random world frame
    (``p_world = R_a p_est / scale + t_a``)."""
    p, R = truth(t + clock)
    Rs, ps = R @ R_bs, p + R @ lever
    phi = rng.normal(size=3)
    if yaw_only:
        phi[:2] = 0.0
    Ra, ta = exp_so3(phi), rng.normal(size=3) * 5.0
    return PoseTrajectory(t, scale * (ps - ta) @ Ra, matrix_to_quat_xyzw(Ra.T @ Rs))


def random_cov(rng: np.random.Generator, sig_pos: float = 3e-3, sig_rot: float = 1e-3):
    """An anisotropic, correlated 6x6 covariance (condition number in scaled units < 9)."""
    Q, _ = np.linalg.qr(rng.normal(size=(6, 6)))
    L = np.r_[[sig_pos] * 3, [sig_rot] * 3][:, None] * Q * rng.uniform(0.5, 1.5, 6)
    return L @ L.T


def errors(fit: MountingFit, *, clock: float = CLOCK) -> np.ndarray:
    """The estimate's error against the truth, in the order of ``fit.names``."""
    e = {"rotation": log_so3(R_BS @ fit.rotation.T), "lever": LEVER - fit.lever,
         "lever-xy": (LEVER - fit.lever)[:2], "clock": np.array([clock - fit.clock_offset])}
    return np.concatenate([e[g] for g in fit.estimated])


# ----------------------------------------------------------------------------- options


def test_estimate_names_aliases_and_rules():
    assert parse_estimate("clock, rotation") == ("rotation", "clock")
    assert parse_estimate("all") == ("rotation", "lever", "clock")
    assert parse_estimate(["mounting", "lever-xy"]) == ("rotation", "lever")
    assert parse_estimate("lever-xy,clock") == ("lever-xy", "clock")
    assert parse_estimate(None) == () and parse_estimate("") == ()
    with pytest.raises(InputError, match="among rotation"):
        parse_estimate("rotations")
    assert EvaluationOptions(estimate="lever,rotation").estimate == ("rotation", "lever")
    with pytest.raises(InputError, match="to estimate"):
        EvaluationOptions(estimate="lever", align="origin")
    with pytest.raises(InputError, match="unit mounting quaternion"):
        EvaluationOptions(mounting=(0, 0, 0, 0, 0, 0, 2.0))
    with pytest.raises(InputError, match="7 finite numbers"):
        EvaluationOptions(mounting=(0, 0, 0, 1))
    m = EvaluationOptions(mounting=(1, 2, 3, 0, 0, 0, -1.0)).mounting
    assert m == (1.0, 2.0, 3.0, 0.0, 0.0, 0.0, 1.0)  # qw >= 0


# ----------------------------------------------------------------------------- exact recovery


@pytest.mark.parametrize(("align", "scale", "yaw_only"),
                         [("none", 1.0, False), ("se3", 1.0, False), ("sim3", 0.7, False),
                          ("4dof", 1.0, True)])
def test_exact_estimate_gives_the_mounting_back(align, scale, yaw_only):
    """Noise-free data: the mounting (174 deg, 0.5 m) and the clock come back to rounding,
    whatever the alignment, from the identity and a zero offset."""
    rng = np.random.default_rng(1)
    t = T0 + 1.0 + 0.1 * np.arange(500)
    est = sensor_estimate(t, rng, scale=scale, yaw_only=yaw_only)
    if align == "none":
        est = sensor_estimate(t, rng, scale=1.0, yaw_only=True)
        p, R = truth(t + CLOCK)
        est = PoseTrajectory(t, p + R @ LEVER, matrix_to_quat_xyzw(R @ R_BS))

    def gt(tau):
        p, R = truth(tau)
        return PoseTrajectory(tau, p, matrix_to_quat_xyzw(R),
                              np.broadcast_to(np.diag([1e-6] * 3 + [1e-8] * 3), (tau.size, 6, 6)))

    res = evaluate(gt, est, align=align, estimate="all", max_dt=None)
    m = res.mounting
    assert np.linalg.norm(log_so3(R_BS @ m.rotation.T)) < 1e-9
    np.testing.assert_allclose(m.lever, LEVER, atol=1e-9)
    assert m.clock_offset == pytest.approx(CLOCK, abs=1e-7)  # the fixed point's tolerance
    assert res.ape.translation_m.rmse < 1e-7 and res.rpe.rotation_deg.rmse < 1e-6
    assert res.association.time_offset == m.clock_offset
    assert m.alignment.method == align and (align != "sim3" or m.alignment.scale == pytest.approx(
        1 / scale, rel=1e-9))
