"""Reference prisms in the chosen body frame, with their propagated covariance."""

import numpy as np
import pytest

from rtsgt.errors import GeometryError
from rtsgt.geometry import RigidTransform, exp_so3
from rtsgt.geometry.transform import perturb
from rtsgt.pose import (
    ReferencePoints,
    check_reference_geometry,
    frame_from_points,
    reference_from_survey,
    triangle_geometry,
)

# a survey like RTS_project's: 3 prisms, 3 GNSS antennas, 2 lidar points, ~10 m away (m)
SURVEY = np.array([
    [10.757, -0.001, 0.282],
    [11.267, 0.463, 0.027],
    [10.278, 0.551, -0.248],
    [10.399, -0.013, -0.479],
    [11.117, 0.186, -0.242],
    [10.946, 0.654, -0.296],
    [10.349, 0.231, -0.456],
    [10.381, 0.361, -0.592],
])


def survey_cov(rng, k=8):
    A = rng.normal(size=(k, 3, 3)) * 0.4e-3
    return A @ np.swapaxes(A, -1, -2) + np.eye(3) * 1e-8


def mc_cov(fn, X, C, rng, M=100_000):
    """Monte Carlo covariance of fn(samples of X (K, 3) with covariance C (3K, 3K))."""
    L = np.linalg.cholesky(C)
    Xs = X + (rng.standard_normal((M, X.size)) @ L.T).reshape(M, *X.shape)
    out = fn(Xs).reshape(M, -1)
    return np.cov(out.T)


def test_survey_frame_is_the_identity():
    rng = np.random.default_rng(1)
    C = survey_cov(rng)
    ref = reference_from_survey(SURVEY, C, [0, 1, 2])
    np.testing.assert_allclose(ref.xyz, SURVEY[:3], atol=1e-12)
    np.testing.assert_allclose(ref.cov_blocks(), C[:3], atol=1e-15)
    assert ref.names == ("1", "2", "3") and ref.frame == "survey"
    np.testing.assert_allclose(ref.cov[:3, 3:], 0.0, atol=1e-18)


def test_transform_frame_maps_points_and_propagates_its_covariance():
    rng = np.random.default_rng(2)
    C = survey_cov(rng)
    R0 = exp_so3([0.1, -0.2, 2.5])
    t0 = np.array([10.5, 0.3, -0.2])
    cov_T = np.diag([1e-6, 2e-6, 3e-6, 1e-5, 2e-5, 4e-6])
    T = RigidTransform(R0, t0, cov_T, frame_to="survey", frame_from="lidar")
    ref = reference_from_survey(SURVEY, C, [2, 0, 1], body_frame=T, names=["c", "a", "b"])
    np.testing.assert_allclose(ref.xyz, (SURVEY[[2, 0, 1]] - t0) @ R0, atol=1e-12)
    assert ref.frame == "lidar" and ref.names == ("c", "a", "b")
    # Monte Carlo over the survey points and the transform (left perturbation, survey frame)
    M = 100_000
    Xs = SURVEY[[2, 0, 1]] + np.einsum(
        "nij,mnj->mni", np.linalg.cholesky(C[[2, 0, 1]]), rng.standard_normal((M, 3, 3)))
    xi = rng.multivariate_normal(np.zeros(6), cov_T, size=M)
    Rs, ts = perturb(R0, t0, xi)
    body = np.einsum("mji,mnj->mni", Rs, Xs - ts[:, None])
    cov_mc = np.cov(body.reshape(M, 9).T)
    assert np.linalg.norm(cov_mc - ref.cov) / np.linalg.norm(ref.cov) < 0.03
    # the transform's uncertainty correlates the prisms
    assert np.abs(ref.cov[:3, 3:6]).max() > 0.2 * np.abs(ref.cov[:3, :3]).max()


def test_frame_from_points_definition():
    rng = np.random.default_rng(3)
    s = SURVEY[3:6]
    R, t = frame_from_points(s)
    np.testing.assert_allclose(R.T @ R, np.eye(3), atol=1e-12)
    assert np.linalg.det(R) == pytest.approx(1.0)
    np.testing.assert_allclose(t, s.mean(0))
    e1 = (s[1] - s[0]) / np.linalg.norm(s[1] - s[0])
    np.testing.assert_allclose(R[:, 0], e1, atol=1e-12)
    n = np.cross(s[1] - s[0], s[2] - s[0])
    np.testing.assert_allclose(R[:, 2], n / np.linalg.norm(n), atol=1e-12)
    # the sensor points lie in the body x-y plane
    body = (s - t) @ R
    np.testing.assert_allclose(body[:, 2], 0.0, atol=1e-12)
    # frames move with the points (equivariance under a rigid motion)
    Q = exp_so3(rng.normal(size=3))
    R2, t2 = frame_from_points(s @ Q.T + 1.0)
    np.testing.assert_allclose(R2, Q @ R, atol=1e-12)
    np.testing.assert_allclose(t2, Q @ t + 1.0, atol=1e-12)
    with pytest.raises(GeometryError, match="collinear"):
        frame_from_points(np.array([[0.0, 0, 0], [1, 0, 0], [2, 1e-6, 0]]))


def test_sensor_points_frame_covariance_includes_the_frame_uncertainty():
    rng = np.random.default_rng(4)
    C = survey_cov(rng)
    Cfull = np.zeros((24, 24))
    for i in range(8):
        Cfull[3 * i:3 * i + 3, 3 * i:3 * i + 3] = C[i]
    ref = reference_from_survey(SURVEY, Cfull, [0, 1, 2], body_frame=[3, 4, 5])
    R, t = frame_from_points(SURVEY[3:6])
    np.testing.assert_allclose(ref.xyz, (SURVEY[:3] - t) @ R, atol=1e-12)
    # distances are frame independent
    d = [np.linalg.norm(SURVEY[i] - SURVEY[j]) for i, j in ((0, 1), (0, 2), (1, 2))]
    np.testing.assert_allclose(ref.distances(), d, atol=1e-12)

    def fn(Xs):
        Rs, ts = frame_from_points(Xs[:, 3:6])
        return np.einsum("mji,mnj->mni", Rs, Xs[:, :3] - ts[:, None])

    cov_mc = mc_cov(fn, SURVEY, Cfull, rng)
    assert np.linalg.norm(cov_mc - ref.cov) / np.linalg.norm(ref.cov) < 0.03
    # larger than the points' own covariance (the frame adds), and correlated across prisms
    assert np.trace(ref.cov) > 1.5 * sum(np.trace(C[i]) for i in range(3))
    assert np.abs(ref.cov[:3, 3:6]).max() > 0.1 * np.abs(ref.cov[:3, :3]).max()


def test_nearly_collinear_reference_raises_with_angle_and_area():
    tri = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.5, 0.03, 0.0]])
    area, angle = triangle_geometry(tri)
    assert area == pytest.approx(0.015)
    assert angle == pytest.approx(np.degrees(np.arctan(0.06)), rel=1e-9)
    with pytest.raises(GeometryError, match=r"area 0\.015 m\^2, smallest angle 3\.43 deg"):
        check_reference_geometry(tri)
    with pytest.raises(GeometryError, match="collinear"):
        ReferencePoints(("1", "2", "3"), tri, np.eye(9) * 1e-6)
    X = np.vstack([tri, SURVEY[3:]])
    with pytest.raises(GeometryError, match="collinear"):
        reference_from_survey(X, np.broadcast_to(np.eye(3) * 1e-8, (8, 3, 3)), [0, 1, 2])
    check_reference_geometry(SURVEY[:3])  # the real triangle passes


def test_fewer_than_three_prisms_raise():
    C = np.broadcast_to(np.eye(3) * 1e-8, (8, 3, 3))
    with pytest.raises(GeometryError, match="at least 3"):
        reference_from_survey(SURVEY, C, [0, 1])
    with pytest.raises(GeometryError, match="at least 3"):
        ReferencePoints(("1", "2"), SURVEY[:2], np.eye(6) * 1e-8)


def test_reference_points_validation_and_select():
    cov = np.eye(9) * 1e-6
    cov[0, 3] = cov[3, 0] = 5e-7
    ref = ReferencePoints(("a", "b", "c"), SURVEY[:3], cov)
    sub = ref.select(["c", "a", "b"])
    np.testing.assert_allclose(sub.xyz, SURVEY[[2, 0, 1]])
    assert sub.cov[3, 6] == 5e-7 and sub.cov[0, 0] == 1e-6
    assert sub.pairs == ((0, 1), (0, 2), (1, 2))
    with pytest.raises(ValueError, match="names"):
        ReferencePoints(("a", "b"), SURVEY[:3], cov)
    with pytest.raises(ValueError, match="positive semi-definite"):
        ReferencePoints(("a", "b", "c"), SURVEY[:3], -cov)
    with pytest.raises(ValueError, match="among"):
        ref.select(["z"])
    with pytest.raises(ValueError, match="body_frame"):
        reference_from_survey(SURVEY, np.broadcast_to(np.eye(3) * 1e-8, (8, 3, 3)), [0, 1, 2],
                              body_frame="lidar")
    with pytest.raises(ValueError, match="0-based"):
        reference_from_survey(SURVEY, np.broadcast_to(np.eye(3) * 1e-8, (8, 3, 3)), [0, 1, 8])
    # read-only arrays
    with pytest.raises(ValueError):
        ref.xyz[0, 0] = 1.0
