"""Synthetic trajectories with covariances for the evaluation tests (helpers + their checks).

Imported by the other ``test_evaluation*`` and ``test_cli_evaluate`` files
(``from test_evaluation_synth import ...``; pytest puts ``tests/`` on ``sys.path``).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from rtsgt.geometry.so3 import matrix_to_quat_xyzw
from rtsgt.geometry.transform import perturb, perturbation
from rtsgt.io.trajectory import write_covariance_csv, write_tum
from rtsgt.types import PoseTrajectory

T0 = 1_668_095_037.0  # an epoch of the real excerpt: times keep their float64 precision


def smooth_truth(n: int = 2000, dt: float = 0.1, t0: float = T0):
    """A smooth 3-D drive (times s, positions m, rotations): Lissajous loop, yaw along the path."""
    s = dt * np.arange(n)
    p = np.c_[
        20 * np.sin(s / 30) + 0.3 * np.sin(s / 3),
        15 * np.sin(s / 20) * np.cos(s / 45),
        0.5 * np.sin(s / 10),
    ]
    v = np.gradient(p, s, axis=0)
    yaw = np.unwrap(np.arctan2(v[:, 1], v[:, 0]))
    roll = 0.05 * np.sin(s / 4)
    pitch = 0.04 * np.cos(s / 5)
    R = Rotation.from_euler("ZYX", np.c_[yaw, pitch, roll]).as_matrix()
    return t0 + s, p, R


def random_covariances(n: int, rng: np.random.Generator, sig_pos=3e-3, sig_rot=1e-3) -> np.ndarray:
    """Anisotropic, correlated SPD 6x6 covariances (x, y, z, rx, ry, rz), m^2 / rad^2.

    ``cov = D Q diag(u^2) Q^T D`` with ``D = diag(sig_pos x 3, sig_rot x 3)``, ``Q`` a random
    orthogonal matrix (position-rotation correlations) and ``u`` in [0.5, 1.5]: the condition
    number in scaled coordinates stays below 9, like the covariances of a real pose fit.
    """
    scale = np.r_[[sig_pos] * 3, [sig_rot] * 3]
    Q, _ = np.linalg.qr(rng.normal(size=(n, 6, 6)))
    L = scale[None, :, None] * Q * rng.uniform(0.5, 1.5, size=(n, 1, 6))
    return L @ np.swapaxes(L, 1, 2)


def sample_xi(cov: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """One draw of xi ~ N(0, cov_k) per pose, (n, 6)."""
    L = np.linalg.cholesky(cov)
    return np.einsum("kij,kj->ki", L, rng.normal(size=cov.shape[:2]))


def trajectory(t, p, R, cov=None) -> PoseTrajectory:
    return PoseTrajectory(t, p, matrix_to_quat_xyzw(R), cov)


def perturbed(t, p, R, cov, rng, *, report=None) -> PoseTrajectory:
    """Truth perturbed by xi ~ N(0, cov) (world-frame left perturbation), reporting ``report``."""
    Rn, pn = perturb(R, p, sample_xi(cov, rng))
    return trajectory(t, pn, Rn, cov if report is None else report)


def transform_trajectory(traj: PoseTrajectory, R_a, t_a, s=1.0) -> PoseTrajectory:
    """``T_a`` applied on the left (positions s R p + t, rotations R R_i, covariance mapped)."""
    Rr = R_a @ traj.rotation
    cov = None
    if traj.cov is not None:
        J = np.zeros((6, 6))
        J[:3, :3] = s * R_a
        J[3:, 3:] = R_a
        cov = J @ traj.cov @ J.T
    return PoseTrajectory(traj.t, s * traj.position @ R_a.T + t_a, matrix_to_quat_xyzw(Rr), cov)


def write_gt_dir(directory: Path, gt: PoseTrajectory) -> Path:
    """An rtsgt output directory holding groundtruth.tum and groundtruth_covariance.csv."""
    directory.mkdir(parents=True, exist_ok=True)
    write_tum(directory / "groundtruth.tum", gt)
    write_covariance_csv(directory / "groundtruth_covariance.csv", gt)
    return directory


def test_sampled_perturbations_reproduce_the_covariance():
    """The generator itself: perturb() with xi ~ N(0, cov) gives a cloud whose perturbation()
    has covariance cov (the convention of rtsgt.geometry.transform)."""
    rng = np.random.default_rng(0)
    t, p, R = smooth_truth(3)
    cov = random_covariances(1, rng)[0]
    M = 40000
    xi = sample_xi(np.broadcast_to(cov, (M, 6, 6)), rng)
    Rs, ps = perturb(R[1], p[1], xi)
    back = perturbation(R[1], p[1], Rs, ps)
    np.testing.assert_allclose(back, xi, atol=1e-12)
    emp = np.cov(back.T)
    # 40000 samples: relative standard error of a variance ~ sqrt(2/M) = 0.7 %
    np.testing.assert_allclose(np.diag(emp), np.diag(cov), rtol=0.04)


def test_truth_is_smooth_and_rotations_proper():
    t, p, R = smooth_truth(500)
    assert np.all(np.diff(t) > 0)
    np.testing.assert_allclose(np.linalg.det(R), 1.0, atol=1e-12)
    step = np.linalg.norm(np.diff(p, axis=0), axis=1)
    assert step.max() < 0.2 and step.min() > 0.01  # 0.1-2 m/s at 10 Hz
