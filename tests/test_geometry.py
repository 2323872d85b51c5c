"""Convention pins and properties of rtsgt.geometry (SO(3), the pose covariance, Kabsch)."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from rtsgt.errors import GeometryError
from rtsgt.geometry import RigidTransform, exp_so3, hat, kabsch, kabsch_yaw, log_so3
from rtsgt.geometry.so3 import matrix_to_quat_xyzw, quat_xyzw_to_matrix
from rtsgt.geometry.transform import check_covariance, perturb, perturbation


def test_hat_is_cross_product():
    rng = np.random.default_rng(1)
    a, b = rng.normal(size=(2, 50, 3))
    np.testing.assert_allclose(hat(a) @ b[..., None], np.cross(a, b)[..., None], atol=1e-15)


def test_exp_matches_scipy_and_log_inverts_it():
    rng = np.random.default_rng(2)
    phi = rng.normal(size=(200, 3))
    phi *= (rng.uniform(0, np.pi - 1e-3, 200) / np.linalg.norm(phi, axis=1))[:, None]
    phi[:5] *= 1e-9  # Taylor branch
    R = exp_so3(phi)
    np.testing.assert_allclose(R, Rotation.from_rotvec(phi).as_matrix(), atol=1e-12)
    np.testing.assert_allclose(log_so3(R), phi, atol=1e-9)


def test_quaternion_is_scalar_last():
    # 90 deg about z: (0, 0, sin 45, cos 45)
    q = matrix_to_quat_xyzw(exp_so3([0, 0, np.pi / 2]))
    np.testing.assert_allclose(q, [0, 0, np.sqrt(0.5), np.sqrt(0.5)], atol=1e-12)
    np.testing.assert_allclose(quat_xyzw_to_matrix(q), exp_so3([0, 0, np.pi / 2]), atol=1e-12)


def test_left_perturbation_convention_reproduces_covariance():
    """A cloud sampled as R = exp(dtheta) R_mean, t = t_mean + dt has the stated covariance."""
    rng = np.random.default_rng(3)
    R0, t0 = exp_so3([0.3, -1.0, 2.0]), np.array([10.0, -4.0, 1.0])
    A = rng.normal(size=(6, 6)) * np.r_[[1e-2] * 3, [1e-3] * 3][:, None]
    cov = A @ A.T
    xi = rng.multivariate_normal(np.zeros(6), cov, size=100_000)
    R, t = perturb(R0, t0, xi)
    # the rotation acts on the left, in the world frame: R R0^T = exp(dtheta)
    np.testing.assert_allclose(log_so3(R[:3] @ R0.T), xi[:3, 3:], atol=1e-12)
    back = perturbation(R0, t0, R, t)
    np.testing.assert_allclose(back, xi, atol=1e-10)
    rel = np.linalg.norm(np.cov(back.T) - cov) / np.linalg.norm(cov)
    assert rel < 0.02


def test_inverse_covariance_matches_monte_carlo():
    rng = np.random.default_rng(4)
    R0, t0 = exp_so3([0.5, 0.2, -2.5]), np.array([3.0, 40.0, -2.0])
    cov = np.diag([1e-6, 4e-6, 9e-6, 1e-7, 2e-7, 3e-7])
    T = RigidTransform(R0, t0, cov)
    Ti = T.inverse()
    np.testing.assert_allclose(Ti.as_matrix(), np.linalg.inv(T.as_matrix()), atol=1e-12)
    xi = rng.multivariate_normal(np.zeros(6), cov, size=200_000)
    R, t = perturb(R0, t0, xi)
    Ri = np.swapaxes(R, -1, -2)
    ti = -np.einsum("nij,nj->ni", Ri, t)
    e = perturbation(Ti.rotation, Ti.translation, Ri, ti)
    rel = np.linalg.norm(np.cov(e.T) - Ti.covariance) / np.linalg.norm(Ti.covariance)
    assert rel < 0.02


def test_rigid_transform_validates():
    with pytest.raises(ValueError, match="proper rotation"):
        RigidTransform(np.diag([1.0, 1.0, -1.0]), np.zeros(3))
    with pytest.raises(ValueError, match=r"shape \(3,\)"):
        RigidTransform(np.eye(3), np.zeros(4))
    with pytest.raises(ValueError, match="symmetric"):
        RigidTransform(np.eye(3), np.zeros(3), np.triu(np.ones((6, 6))))
    with pytest.raises(ValueError, match="positive semi-definite"):
        check_covariance(-np.eye(3), 3)


def test_kabsch_recovers_transform_and_guards_reflection():
    rng = np.random.default_rng(5)
    R = exp_so3(rng.normal(size=(100, 3)))
    t = rng.normal(size=(100, 3)) * 10
    p = rng.normal(size=(100, 6, 3))
    q = np.einsum("bij,bnj->bni", R, p) + t[:, None]
    R2, t2 = kabsch(p, q)
    np.testing.assert_allclose(R2, R, atol=1e-10)
    np.testing.assert_allclose(t2, t, atol=1e-9)
    # a mirrored target must still give a proper rotation (det +1), never a reflection
    q_mirror = q * np.array([1.0, 1.0, -1.0])
    R3, _ = kabsch(p, q_mirror)
    np.testing.assert_allclose(np.linalg.det(R3), 1.0, atol=1e-10)


def test_kabsch_weighted_equals_duplicated_points():
    rng = np.random.default_rng(6)
    p = rng.normal(size=(5, 3))
    q = p @ exp_so3([0.1, 0.2, 0.3]).T + rng.normal(size=(5, 3)) * 0.05
    w = np.array([1, 2, 1, 3, 1])
    R1, t1 = kabsch(p, q, w)
    R2, t2 = kabsch(np.repeat(p, w, axis=0), np.repeat(q, w, axis=0))
    np.testing.assert_allclose(R1, R2, atol=1e-12)
    np.testing.assert_allclose(t1, t2, atol=1e-12)


def test_kabsch_rejects_degenerate_input():
    p = np.array([[0.0, 0, 0], [1, 0, 0], [2, 0, 0]])
    with pytest.raises(GeometryError, match="collinear"):
        kabsch(p, p)
    with pytest.raises(GeometryError, match="at least 3"):
        kabsch(p[:2], p[:2])


def test_kabsch_yaw_recovers_yaw_and_minimises_the_weighted_cost():
    """Exact data: the yaw and translation back, batched; noisy data: no rotation about z
    nearby gives a smaller weighted cost (a second engine: brute force over the yaw)."""
    rng = np.random.default_rng(8)
    yaw = rng.uniform(-np.pi, np.pi, 50)
    R = exp_so3(np.stack([np.zeros(50), np.zeros(50), yaw], axis=1))
    t = rng.normal(size=(50, 3)) * 20
    p = rng.normal(size=(50, 5, 3)) * 10
    q = np.einsum("bij,bnj->bni", R, p) + t[:, None]
    R2, t2 = kabsch_yaw(p, q)
    np.testing.assert_allclose(R2, R, atol=1e-10)
    np.testing.assert_allclose(t2, t, atol=1e-8)
    w = rng.uniform(0.5, 2.0, 5)
    qn = q[0] + rng.normal(size=(5, 3))
    R3, t3 = kabsch_yaw(p[0], qn, w)

    def cost(Rz):
        r = qn - p[0] @ Rz.T
        r -= (w @ r) / w.sum()  # the best translation for this rotation
        return float(w @ np.sum(r ** 2, axis=1))

    best = cost(R3)
    psi = np.arctan2(R3[1, 0], R3[0, 0])
    for d in np.linspace(-0.05, 0.05, 41):
        if abs(d) > 1e-9:
            assert cost(exp_so3([0.0, 0.0, psi + d])) > best
    np.testing.assert_allclose(R3[2], [0.0, 0.0, 1.0])


def test_kabsch_yaw_rejects_points_without_horizontal_spread():
    p = np.array([[0.0, 0, 0], [0, 0, 1], [0, 0, 2]])
    with pytest.raises(GeometryError, match="no horizontal spread"):
        kabsch_yaw(p, p)
