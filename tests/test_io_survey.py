"""Readers of the static robot survey, calibration_results.csv and reference-point CSV files."""


import numpy as np
import pytest

from _paths import EXCERPT as DATA
from rtsgt.errors import InputError
from rtsgt.io.survey import (
    read_calibration_results,
    read_reference_csv,
    read_survey_raw,
    write_reference_csv,
)
from rtsgt.pose import ReferencePoints, reference_from_survey

ARCSEC = np.pi / (180 * 3600)


def write(tmp_path, text, name="survey.csv"):
    p = tmp_path / name
    p.write_text(text)
    return p


def test_real_survey_reproduces_the_published_inter_prism_distances():
    s = read_survey_raw(DATA / "calibration_raw.csv")
    c = read_calibration_results(DATA / "calibration_results.csv")
    np.testing.assert_allclose(c.prism_distances, [0.73555, 0.90303, 1.03046], atol=5e-6)
    ref = reference_from_survey(s.xyz, s.cov, [s.index("prism1"), s.index("prism2"),
                                               s.index("prism3")])
    # well under 1 mm (same formula as the authors: equal to rounding)
    np.testing.assert_allclose(ref.distances(), c.prism_distances, atol=1e-9)
    g = [np.linalg.norm(s.xyz[i] - s.xyz[j]) for i, j in ((3, 4), (3, 5), (4, 5))]
    np.testing.assert_allclose(g, c.gnss_distances, atol=1e-9)
    assert len(s) == 9
    assert s.names[:7] == ("prism1", "prism2", "prism3", "gnss1", "gnss2", "gnss3", "lidar1")
    # a GNSS-antenna body frame keeps the distances and gives a correlated covariance
    ref_g = reference_from_survey(s.xyz, s.cov, [0, 1, 2], body_frame=[3, 4, 5])
    np.testing.assert_allclose(ref_g.distances(), c.prism_distances, atol=1e-9)
    assert np.trace(ref_g.cov) > np.trace(ref.cov)


def test_real_survey_matches_the_authors_cartesian_points():
    """Rows 1-6 of sensor_positions.csv are the same shots converted by the reference code."""
    s = read_survey_raw(DATA / "calibration_raw.csv")
    authors = np.loadtxt(DATA / "sensor_positions.csv")[:6, :3]
    np.testing.assert_allclose(s.xyz[:6], authors, atol=1e-9)
    # first row: Hz = 0 00 16, sigma Hz = 0 00 04.769, V = 88 29 47, d = 10.761 +- 0.0006
    assert s.hz[0] == pytest.approx(16 * ARCSEC, rel=1e-12)
    assert s.sigma_hz[0] == pytest.approx(4.769 * ARCSEC, rel=1e-12)
    assert s.v[0] == pytest.approx((88 * 3600 + 29 * 60 + 47) * ARCSEC, rel=1e-12)
    assert s.d[0] == 10.761 and s.sigma_d[0] == 0.0006


def test_manual_shot_convention_and_first_order_covariance(tmp_path):
    # Hz = 90 deg, V = 90 deg: x = d cos Hz sin V = 0, y = -d sin Hz sin V = -d, z = 0
    # Hz = 0, V = 45 deg: x = d / sqrt 2, y = 0, z = d / sqrt 2
    p = write(tmp_path, "90 00 00 0 00 02 90 00 00 0 00 03 5.0 0.001 0\n"
                        "00 00 00 0 00 02 45 00 00 0 00 03 2.0 0.002 0\n"
                        "-0 30 00 0 00 02 90 00 00 0 00 03 3.0 0.002 0\n")
    s = read_survey_raw(p, names=["a", "b", "c"], additive_constant=0.01)
    np.testing.assert_allclose(s.xyz[0], [0.0, -5.01, 0.0], atol=1e-12)
    np.testing.assert_allclose(s.xyz[1], [2.01 / np.sqrt(2), 0.0, 2.01 / np.sqrt(2)], atol=1e-12)
    assert s.hz[2] == pytest.approx(-0.5 * np.pi / 180)  # the sign applies to the whole angle
    # at Hz = 90, V = 90 the axes are: x <- Hz, y <- distance, z <- V
    d = 5.01
    np.testing.assert_allclose(
        s.cov[0], np.diag([(d * 2 * ARCSEC) ** 2, 0.001**2, (d * 3 * ARCSEC) ** 2]), atol=1e-20
    )
    # Monte Carlo of the exact conversion agrees with the first-order covariance
    rng = np.random.default_rng(1)
    M = 200_000
    hz = s.hz[1] + rng.normal(size=M) * s.sigma_hz[1]
    v = s.v[1] + rng.normal(size=M) * s.sigma_v[1]
    dd = s.d[1] + rng.normal(size=M) * s.sigma_d[1]
    xyz = np.stack([dd * np.cos(hz) * np.sin(v), -dd * np.sin(hz) * np.sin(v), dd * np.cos(v)])
    np.testing.assert_allclose(np.cov(xyz), s.cov[1], atol=0.02 * np.abs(s.cov[1]).max())
    big = s.cov_stacked()
    assert big.shape == (9, 9)
    np.testing.assert_allclose(big[3:6, 3:6], s.cov[1])


@pytest.mark.parametrize(
    "line, message",
    [
        ("00 00 16 0 00 04.769 88 29 47 0 00 01.457 10.761 0.0006", "expected 15"),
        ("00 00 16 0 00 04.769 88 29 47 0 00 01.457 10.761 x 0", "sigma_distance"),
        ("00 61 16 0 00 04.769 88 29 47 0 00 01.457 10.761 0.0006 0", "minutes"),
        ("00 00 60 0 00 04.769 88 29 47 0 00 01.457 10.761 0.0006 0", "seconds"),
        ("00 00 16 0 00 04.769 188 29 47 0 00 01.457 10.761 0.0006 0", "zenith"),
        ("00 00 16 0 00 04.769 88 29 47 0 00 01.457 -1.0 0.0006 0", "positive distance"),
        ("00 00 16 0 00 04.769 88 29 47 0 00 01.457 10.761 -0.0006 0", "non-negative"),
        ("0.5 00 16 0 00 04.769 88 29 47 0 00 01.457 10.761 0.0006 0", "whole degrees"),
    ],
)
def test_survey_errors_name_file_and_line(tmp_path, line, message):
    good = "00 00 16 0 00 04.769 88 29 47 0 00 01.457 10.761 0.0006 0\n"
    p = write(tmp_path, "# survey\n" + good + line + "\n")
    with pytest.raises(InputError, match=message) as exc:
        read_survey_raw(p)
    assert exc.value.line == 3 and str(p) in str(exc.value)


def test_survey_missing_file_and_names_count(tmp_path):
    with pytest.raises(InputError, match="not found"):
        read_survey_raw(tmp_path / "nope.csv")
    p = write(tmp_path, "00 00 16 0 00 04.769 88 29 47 0 00 01.457 10.761 0.0006 0\n")
    with pytest.raises(InputError, match="one per name"):
        read_survey_raw(p, names=["a", "b"])


def test_calibration_results_reader(tmp_path):
    c = read_calibration_results(write(tmp_path, "0.7 0.9 1.0\n", "c.csv"))
    np.testing.assert_allclose(c.prism_distances, [0.7, 0.9, 1.0])
    assert c.gnss_distances is None
    c = read_calibration_results(write(tmp_path, "0.7,0.9,1.0,0.5,0.6,0.8\n", "c.csv"))
    np.testing.assert_allclose(c.gnss_distances, [0.5, 0.6, 0.8])
    with pytest.raises(InputError, match="3 or 6"):
        read_calibration_results(write(tmp_path, "0.7 0.9\n", "c.csv"))
    with pytest.raises(InputError, match="one line") as exc:
        read_calibration_results(write(tmp_path, "0.7 0.9 1.0\n0.7 0.9 1.0\n", "c.csv"))
    assert exc.value.line == 2
    with pytest.raises(InputError, match="positive distance d13"):
        read_calibration_results(write(tmp_path, "0.7 -0.9 1.0\n", "c.csv"))


def test_reference_csv_round_trip_and_errors(tmp_path):
    xyz = np.array([[0.1, 0.2, 0.6], [0.8, 0.2, 0.6], [0.4, 1.0, 0.65]])
    blocks = np.array([np.diag([1e-7, 2e-7, 3e-7]) + 1e-8 for _ in range(3)])
    ref = ReferencePoints(("p1", "p2", "p3"), xyz, blocks, "robot")
    path = tmp_path / "ref.csv"
    write_reference_csv(path, ref)
    back = read_reference_csv(path, frame="robot")
    assert back.names == ref.names and back.frame == "robot"
    np.testing.assert_array_equal(back.xyz, ref.xyz)
    np.testing.assert_array_equal(back.cov, ref.cov)
    # any column order, comments allowed
    p = write(tmp_path, "# reference\nx,name,y,z,cov_xx,cov_xy,cov_xz,cov_yy,cov_yz,cov_zz\n"
                        "0.1,a,0.2,0.6,1e-6,0,0,1e-6,0,1e-6\n"
                        "0.8,b,0.2,0.6,1e-6,0,0,1e-6,0,1e-6\n"
                        "0.4,c,1.0,0.6,1e-6,0,0,1e-6,0,1e-6\n", "r.csv")
    r = read_reference_csv(p)
    np.testing.assert_allclose(r.xyz[1], [0.8, 0.2, 0.6])
    head = "name,x,y,z,cov_xx,cov_xy,cov_xz,cov_yy,cov_yz,cov_zz\n"
    rows = ["a,0.1,0.2,0.6,1e-6,0,0,1e-6,0,1e-6", "b,0.8,0.2,0.6,1e-6,0,0,1e-6,0,1e-6",
            "c,0.4,1.0,0.6,1e-6,0,0,1e-6,0,1e-6"]
    with pytest.raises(InputError, match="duplicated point name 'a'") as exc:
        read_reference_csv(write(tmp_path, head + "\n".join(rows + [rows[0]]) + "\n", "r.csv"))
    assert exc.value.line == 5
    bad = rows[:1] + ["b,0.8,0.2,0.6,1e-6,5e-6,0,1e-6,0,1e-6"] + rows[2:]
    with pytest.raises(InputError, match="positive semi-definite covariance for 'b'") as exc:
        read_reference_csv(write(tmp_path, head + "\n".join(bad) + "\n", "r.csv"))
    assert exc.value.line == 3
    with pytest.raises(InputError, match="missing column"):
        read_reference_csv(write(tmp_path, "name,x,y,z\na,0,0,0\n", "r.csv"))
    with pytest.raises(InputError, match="number in column 'y'") as exc:
        text = head + rows[0] + "\nb,0.8,oops,0.6,1e-6,0,0,1e-6,0,1e-6\n" + rows[2] + "\n"
        read_reference_csv(write(tmp_path, text, "r.csv"))
    assert exc.value.line == 3
    collinear = ["a,0,0,0,1e-6,0,0,1e-6,0,1e-6", "b,1,0,0,1e-6,0,0,1e-6,0,1e-6",
                 "c,2,0.001,0,1e-6,0,0,1e-6,0,1e-6"]
    with pytest.raises(InputError, match="collinear"):
        read_reference_csv(write(tmp_path, head + "\n".join(collinear) + "\n", "r.csv"))
    with pytest.raises(InputError, match="at least 3"):
        read_reference_csv(write(tmp_path, head + "\n".join(rows[:2]) + "\n", "r.csv"))
    # a correlated covariance cannot be written in this format
    cov = ref.cov.copy()
    cov[0, 3] = cov[3, 0] = 1e-8
    with pytest.raises(ValueError, match="block-diagonal"):
        write_reference_csv(path, ReferencePoints(ref.names, xyz, cov))
