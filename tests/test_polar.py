"""The station-frame convention: zenith angle, clockwise horizontal direction."""

import numpy as np
from hypothesis import given
from hypothesis import strategies as st

from rtsgt.measurement.polar import cartesian_to_polar, polar_jacobian, polar_to_cartesian


def test_convention_pins():
    # Hz = 0 looks along +y, Hz = 90 deg (clockwise) along +x; V = 0 is straight up
    np.testing.assert_allclose(polar_to_cartesian(0.0, np.pi / 2, 10.0), [0, 10, 0], atol=1e-12)
    np.testing.assert_allclose(polar_to_cartesian(np.pi / 2, np.pi / 2, 10.0), [10, 0, 0], atol=1e-12)
    np.testing.assert_allclose(polar_to_cartesian(1.0, 0.0, 5.0), [0, 0, 5], atol=1e-12)
    # below the horizon (V > 90 deg) is negative z
    assert polar_to_cartesian(0.3, 1.7, 20.0)[2] < 0


@given(
    hz=st.floats(0, 2 * np.pi - 1e-9),
    v=st.floats(0.01, np.pi - 0.01),
    d=st.floats(0.5, 3000),
)
def test_round_trip(hz, v, d):
    h2, v2, d2 = cartesian_to_polar(polar_to_cartesian(hz, v, d))
    assert abs(d2 - d) < 1e-9 * d
    assert abs(v2 - v) < 1e-9
    assert abs(np.angle(np.exp(1j * (h2 - hz)))) < 1e-8


def test_jacobian_matches_central_differences():
    rng = np.random.default_rng(0)
    x = np.stack([rng.uniform(0, 2 * np.pi, 50), rng.uniform(0.2, 2.9, 50), rng.uniform(2, 900, 50)], 1)
    J = polar_jacobian(*x.T)
    h = np.array([1e-7, 1e-7, 1e-6])
    num = np.empty_like(J)
    for j in range(3):
        dx = np.zeros(3)
        dx[j] = h[j]
        num[..., j] = (polar_to_cartesian(*(x + dx).T) - polar_to_cartesian(*(x - dx).T)) / (2 * h[j])
    np.testing.assert_allclose(J, num, rtol=1e-6, atol=1e-6)
