"""The survey (manual-shot) polar convention of rtsgt.measurement.polar, pinned against the
tracking convention."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from rtsgt.measurement.polar import (
    R_SURVEY_TRACKING,
    cartesian_to_survey_polar,
    polar_jacobian,
    polar_to_cartesian,
    survey_polar_jacobian,
    survey_polar_to_cartesian,
)


def test_survey_convention_pins():
    # x = d cos Hz sin V, y = -d sin Hz sin V, z = d cos V
    np.testing.assert_allclose(survey_polar_to_cartesian(0.0, np.pi / 2, 10.0), [10, 0, 0],
                               atol=1e-12)
    # Hz = 90 deg clockwise: -y
    np.testing.assert_allclose(survey_polar_to_cartesian(np.pi / 2, np.pi / 2, 10.0),
                               [0, -10, 0], atol=1e-12)
    np.testing.assert_allclose(survey_polar_to_cartesian(1.0, 0.0, 5.0), [0, 0, 5], atol=1e-12)
    rng = np.random.default_rng(0)
    hz, v, d = rng.uniform(0, 2 * np.pi, 50), rng.uniform(0.1, 3.0, 50), rng.uniform(1, 90, 50)
    expected = np.stack([d * np.cos(hz) * np.sin(v), -d * np.sin(hz) * np.sin(v), d * np.cos(v)],
                        axis=-1)
    np.testing.assert_allclose(survey_polar_to_cartesian(hz, v, d), expected, rtol=0, atol=1e-12)


def test_survey_frame_is_the_tracking_frame_rotated_about_z():
    # p_survey = Rz(-90 deg) p_tracking for the same (Hz, V, d)
    rz = Rotation.from_euler("z", -90.0, degrees=True).as_matrix()
    np.testing.assert_allclose(R_SURVEY_TRACKING, rz, atol=1e-15)
    rng = np.random.default_rng(1)
    hz, v, d = rng.uniform(0, 2 * np.pi, 50), rng.uniform(0.1, 3.0, 50), rng.uniform(1, 90, 50)
    tracking = polar_to_cartesian(hz, v, d)
    np.testing.assert_allclose(survey_polar_to_cartesian(hz, v, d), tracking @ rz.T, atol=1e-12)
    np.testing.assert_allclose(survey_polar_jacobian(hz, v, d), rz @ polar_jacobian(hz, v, d),
                               atol=1e-12)
    # survey x = tracking y, survey y = -tracking x
    p = survey_polar_to_cartesian(hz, v, d)
    np.testing.assert_array_equal(p[:, 0], tracking[:, 1])
    np.testing.assert_array_equal(p[:, 1], -tracking[:, 0])


def test_survey_round_trip_and_jacobian():
    rng = np.random.default_rng(2)
    hz, v, d = rng.uniform(0, 2 * np.pi, 200), rng.uniform(0.1, 3.0, 200), rng.uniform(1, 90, 200)
    h2, v2, d2 = cartesian_to_survey_polar(survey_polar_to_cartesian(hz, v, d))
    assert np.all((h2 >= 0) & (h2 < 2 * np.pi))
    np.testing.assert_allclose(np.angle(np.exp(1j * (h2 - hz))), 0.0, atol=1e-12)
    np.testing.assert_allclose(v2, v, atol=1e-12)
    np.testing.assert_allclose(d2, d, rtol=1e-14)
    # the Jacobian is the derivative of the conversion (central differences)
    eps = 1e-6
    J = survey_polar_jacobian(hz, v, d)
    for j in range(3):
        step = np.zeros(3)
        step[j] = eps
        plus = survey_polar_to_cartesian(hz + step[0], v + step[1], d + step[2])
        minus = survey_polar_to_cartesian(hz - step[0], v - step[1], d - step[2])
        np.testing.assert_allclose(J[..., j], (plus - minus) / (2 * eps), atol=1e-6)


def test_survey_constant_is_read_only():
    with pytest.raises(ValueError):
        R_SURVEY_TRACKING[0, 0] = 1.0
