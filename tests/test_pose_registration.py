"""The fast closed-form registration against the SVD Kabsch, and its analytic Jacobian."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from rtsgt.errors import GeometryError
from rtsgt.geometry import exp_so3, kabsch, log_so3
from rtsgt.geometry.transform import perturbation
from rtsgt.pose import register, registration_jacobian, shape_ratio
from rtsgt.pose.registration import small_rotation_vector


def _problems(rng, B, N, noise, scale=(1.0, 0.7, 0.3), rotations=None):
    p = rng.normal(size=(B, N, 3)) * np.asarray(scale)
    R = Rotation.random(B, random_state=rng).as_matrix() if rotations is None else rotations
    t = rng.normal(size=(B, 3)) * 100.0
    q = np.einsum("bij,bnj->bni", R, p) + t[:, None, :] + rng.normal(size=(B, N, 3)) * noise
    return p, q


def _assert_same_as_svd(p, q, tol=1e-9):
    R, t = register(p, q)
    R_svd, t_svd = kabsch(p, q, check=False)
    np.testing.assert_allclose(R, R_svd, atol=tol, rtol=0)
    np.testing.assert_allclose(t, t_svd, atol=tol * 100, rtol=0)  # |t| ~ 100 m
    # and it is a proper rotation
    np.testing.assert_allclose(R @ np.swapaxes(R, -1, -2), np.broadcast_to(np.eye(3), R.shape),
                               atol=1e-9)
    assert np.all(np.linalg.det(R) > 0)


@pytest.mark.parametrize("N", [3, 4, 7])
@pytest.mark.parametrize("noise", [0.0, 0.003, 0.2])
def test_matches_svd_kabsch_random(N, noise):
    rng = np.random.default_rng(100 + N)
    p, q = _problems(rng, 20_000, N, noise)
    _assert_same_as_svd(p, q)


def test_matches_svd_near_180_degrees():
    rng = np.random.default_rng(1)
    B = 5000
    axis = rng.normal(size=(B, 3))
    axis /= np.linalg.norm(axis, axis=1, keepdims=True)
    angle = np.pi - 10.0 ** rng.uniform(-9, -1, B)
    angle[:100] = np.pi  # exactly 180 degrees
    R_true = exp_so3(axis * angle[:, None])
    for N in (3, 5):
        for noise in (0.0, 0.002):
            p, q = _problems(rng, B, N, noise, rotations=R_true)
            _assert_same_as_svd(p, q)
    # noise-free: the rotation is recovered exactly through 180 degrees
    p, q = _problems(rng, B, 3, 0.0, rotations=R_true)
    R, _ = register(p, q)
    np.testing.assert_allclose(R, R_true, atol=1e-9)


def test_matches_svd_on_reflected_noisy_data():
    """Least squares over proper rotations when the data are a mirror image (det guard)."""
    rng = np.random.default_rng(2)
    mirror = np.diag([1.0, 1.0, -1.0])
    for N in (3, 4, 6):
        p, q = _problems(rng, 10_000, N, 0.01, scale=(1.0, 0.6, 0.25))
        q = q @ mirror
        _assert_same_as_svd(p, q)


def test_minimises_the_sum_of_squares():
    """No rotation near the solution does better (a direct check of optimality)."""
    rng = np.random.default_rng(3)
    p, q = _problems(rng, 200, 3, 0.05)
    R, t = register(p, q)

    def cost(R_, t_):
        r = q - (np.einsum("bij,bnj->bni", R_, p) + t_[:, None])
        return np.sum(r * r, axis=(1, 2))

    c0 = cost(R, t)
    for _ in range(20):
        dR = exp_so3(rng.normal(size=(200, 3)) * 1e-3)
        R2 = dR @ R
        t2 = q.mean(1) - np.einsum("bij,bj->bi", R2, p.mean(1))
        assert np.all(cost(R2, t2) >= c0 - 1e-12)


def test_chunking_batch_shapes_and_nan():
    rng = np.random.default_rng(4)
    p, q = _problems(rng, 1000, 3, 0.01)
    R1, t1 = register(p, q)
    R2, t2 = register(p, q, chunk_size=7)  # same up to rounding (Newton stops per chunk)
    np.testing.assert_allclose(R1, R2, atol=1e-10)
    np.testing.assert_allclose(t1, t2, atol=1e-8)
    R3, t3 = register(p.reshape(10, 100, 3, 3), q.reshape(10, 100, 3, 3))
    np.testing.assert_array_equal(R3.reshape(1000, 3, 3), R1)
    q[5, 1, 2] = np.nan
    R4, t4, info = register(p, q, return_info=True)
    assert np.all(np.isnan(R4[5])) and np.all(np.isnan(t4[5]))
    assert info.degenerate[5] and not info.degenerate[4]
    np.testing.assert_allclose(R4[:5], R1[:5], atol=1e-10)


def test_degenerate_collinear_detected_per_element():
    rng = np.random.default_rng(5)
    tri = np.array([[0.0, 0.0, 0.0], [0.74, 0.0, 0.0], [0.3, 0.85, 0.05]])
    p = tri + rng.normal(size=(100, 3, 3)) * 0.01
    R_true = Rotation.random(100, random_state=rng).as_matrix()
    q = np.einsum("bij,bnj->bni", R_true, p) + rng.normal(size=(100, 3, 3)) * 0.001
    line = np.array([0.0, 0.5, 1.0])[:, None] * np.array([1.0, 2.0, 0.5])
    p[7] = line
    q[7] = line + 3.0
    p[9] = line + rng.normal(size=(3, 3)) * 1e-3  # nearly collinear body points
    R, t, info = register(p, q, return_info=True)
    assert info.degenerate[7] and info.degenerate[9]
    assert info.degenerate.sum() == 2
    assert info.shape_body[7] < 1e-6
    assert np.all(np.isfinite(R[7]))  # a minimiser is still returned, flagged
    np.testing.assert_allclose(info.rms[~info.degenerate], 0.0, atol=0.005)


def test_too_few_points_and_bad_shapes():
    with pytest.raises(GeometryError, match="at least 3"):
        register(np.zeros((4, 2, 3)), np.zeros((4, 2, 3)))
    with pytest.raises(ValueError, match="Expected two arrays"):
        register(np.zeros((4, 3, 3)), np.zeros((4, 4, 3)))


def test_shape_ratio_of_a_triangle_closed_form():
    """Base b on the x axis, apex at height h above its middle: ratio = 2 h / (sqrt(3) b)."""
    b = 1.0
    for h in (0.01, 0.1, 0.5):
        tri = np.array([[0.0, 0.0, 0.0], [b, 0.0, 0.0], [b / 2, h, 0.0]])
        assert shape_ratio(tri) == pytest.approx(2 * h / (np.sqrt(3) * b), rel=1e-12)
    assert shape_ratio(np.array([[0.0, 0, 0], [1, 0, 0], [2, 0, 0]])) < 1e-6


def test_jacobian_matches_central_differences():
    rng = np.random.default_rng(6)
    T, N = 6, 4
    p, q = _problems(rng, T, N, 0.05)  # residuals are not zero: the IFT must handle them
    R, t = register(p, q)
    J_q, J_p = registration_jacobian(p, q)
    h = 1e-6
    E = np.eye(3 * N).reshape(3 * N, N, 3) * h
    for which, J in (("q", J_q), ("p", J_p)):
        if which == "q":
            plus = register(np.broadcast_to(p[:, None], (T, 3 * N, N, 3)), q[:, None] + E)
            minus = register(np.broadcast_to(p[:, None], (T, 3 * N, N, 3)), q[:, None] - E)
        else:
            plus = register(p[:, None] + E, np.broadcast_to(q[:, None], (T, 3 * N, N, 3)))
            minus = register(p[:, None] - E, np.broadcast_to(q[:, None], (T, 3 * N, N, 3)))
        xp = perturbation(R[:, None], t[:, None], *plus)
        xm = perturbation(R[:, None], t[:, None], *minus)
        J_fd = ((xp - xm) / (2 * h)).transpose(0, 2, 1).reshape(T, 6, N, 3)
        np.testing.assert_allclose(J, J_fd, atol=1e-7 * np.abs(J).max())


def test_jacobian_rejects_collinear():
    line = np.array([0.0, 0.5, 1.0])[:, None] * np.array([1.0, 2.0, 0.5])
    with pytest.raises(GeometryError):
        registration_jacobian(line, line + 1.0, np.eye(3))


def test_small_rotation_vector_matches_log():
    rng = np.random.default_rng(7)
    phi = rng.normal(size=(2000, 3))
    phi *= rng.uniform(0, 3.1, 2000)[:, None] / np.linalg.norm(phi, axis=1, keepdims=True)
    phi[:10] *= 1e-12
    R = exp_so3(phi)
    np.testing.assert_allclose(small_rotation_vector(R), log_so3(R), atol=1e-10)
