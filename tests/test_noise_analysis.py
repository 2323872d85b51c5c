"""The paper's per-source analysis (sqrt of the Frobenius norm, mm, by range bin).

Closed forms for the norm and the binning, the one-liner of the API, and the real excerpt:
the instrument source of the Trimble S7 at the excerpt's ranges (3 m to 90 m) lands near the
paper's 2.1 mm (docs/paper-figures.md#per-source-medians), with the other sources in the
published order.
"""

from __future__ import annotations

import numpy as np
import pytest

from _paths import EXCERPT as DATA
from rtsgt.calibration import calibrate
from rtsgt.errors import InputError
from rtsgt.io.rts_project import read_gcp_rts_project, read_prism_file
from rtsgt.io.weather import read_weather_eccc
from rtsgt.measurement.instruments import TRIMBLE_S7
from rtsgt.noise import (
    PAPER_RANGE_EDGES,
    NoiseModel,
    authors_source_norms_mm,
    bin_by_range,
    frobenius_norm_mm,
    propagate,
    source_norms_mm,
    summarize_sources,
)
from rtsgt.types import Observations


def test_frobenius_norm_closed_form():
    # diag(a^2, b^2, c^2) m^2: sqrt(||.||_F) = (a^4 + b^4 + c^4)^(1/4) m
    a, b, c = 2e-3, 1e-3, 0.5e-3
    cov = np.diag([a**2, b**2, c**2])
    assert frobenius_norm_mm(cov) == pytest.approx((a**4 + b**4 + c**4) ** 0.25 * 1e3)
    # rank one s^2 u u^T with |u| = 1: exactly s (in mm); rotation invariant
    u = np.array([0.6, 0.0, 0.8])
    R = np.linalg.qr(np.random.default_rng(0).standard_normal((3, 3)))[0]
    covs = np.stack([(1.5e-3) ** 2 * np.outer(u, u), R @ cov @ R.T])
    np.testing.assert_allclose(frobenius_norm_mm(covs),
                               [1.5, (a**4 + b**4 + c**4) ** 0.25 * 1e3], rtol=1e-12)
    with pytest.raises(InputError, match=r"shape \(\.\.\., 3, 3\), got \(2, 2\)"):
        frobenius_norm_mm(np.eye(2))


def test_bin_by_range_medians_counts_and_empty_bins():
    r = np.array([10.0, 20.0, 74.9, 75.0, 100.0, 149.0, np.nan, 30.0])
    v = np.array([1.0, 3.0, 2.0, 5.0, 7.0, 6.0, 100.0, np.nan])
    b = bin_by_range(v, r)
    np.testing.assert_array_equal(b.edges, PAPER_RANGE_EDGES)
    np.testing.assert_array_equal(b.count, [3, 3, 0])  # NaN value or range left out
    np.testing.assert_array_equal(b.median[:2], [2.0, 6.0])
    assert np.isnan(b.median[2])
    assert b.overall_median == 4.0 and b.overall_count == 6
    assert b.labels() == ["0-75 m", "75-150 m", "> 150 m"]
    assert b.as_dict()["median"] == [2.0, 6.0, None]
    several = bin_by_range({"x": v, "y": 2 * v}, r, edges=(0.0, 50.0, 200.0))
    np.testing.assert_array_equal(several["y"].median, [4.0, 11.0])  # 2 x median(2, 5, 7, 6)
    with pytest.raises(InputError, match="increasing bin edges"):
        bin_by_range(v, r, edges=(0.0, 50.0, 50.0))
    with pytest.raises(InputError, match="same shape"):
        bin_by_range(v, r[:3])


def _track(n=40, seed=0):
    rng = np.random.default_rng(seed)
    obs = Observations(t=np.arange(n) * 0.4, hz=rng.uniform(0, 6.28, n),
                       v=rng.uniform(1.2, 1.9, n), d=np.linspace(5.0, 300.0, n))
    return obs


def test_summary_is_a_one_liner_and_matches_the_pieces():
    obs = _track()
    model = NoiseModel(TRIMBLE_S7, sources=("instrument", "tilt", "atmosphere"))
    tr = propagate(obs, model)
    summary = summarize_sources(tr)  # the one-liner
    assert set(summary) == {"instrument", "tilt", "atmosphere", "total"}
    norms = source_norms_mm(tr)
    for s, bins in summary.items():
        for k, (lo, hi) in enumerate(zip(PAPER_RANGE_EDGES[:-1], PAPER_RANGE_EDGES[1:],
                                         strict=True)):
            sel = (tr.range_m >= lo) & (tr.range_m < hi)
            assert bins.count[k] == sel.sum()
            assert bins.median[k] == pytest.approx(np.median(norms[s][sel]))
    # the instrument source alone has the eigenvalues sd^2 (line of sight), (d sa)^2 (zenith
    # angle) and (d sin V sa)^2 (direction): (4 mm + 2 ppm) / 2 = 2.0-2.3 mm dominates
    d = tr.range_m
    sd = TRIMBLE_S7.sigma_distance(obs.d)
    sa = TRIMBLE_S7.sigma_angle * d
    expected = (sd**4 + sa**4 + (sa * np.sin(obs.v)) ** 4) ** 0.25 * 1e3
    np.testing.assert_allclose(norms["instrument"], expected, rtol=1e-9)
    no_range = type(tr)(t=tr.t, xyz=tr.xyz, cov=tr.cov, cov_by_source=tr.cov_by_source)
    with pytest.raises(InputError, match="no range_m"):
        summarize_sources(no_range)


def test_authors_variant_equals_each_source_alone_for_the_linear_engine():
    # first order, the sources add up: Sigma_(instrument + s) - Sigma_instrument = Sigma_s
    # (time synchronisation adds the tiny interaction with the velocity noise)
    obs = _track()
    model = NoiseModel(TRIMBLE_S7, sources=("instrument", "tilt", "atmosphere", "time_sync"))
    alone = source_norms_mm(propagate(obs, model), total=False)
    authors = authors_source_norms_mm(obs, model)
    assert set(authors) == set(alone)
    for s in ("instrument", "tilt", "atmosphere"):
        np.testing.assert_allclose(authors[s], alone[s], rtol=1e-6)
    np.testing.assert_allclose(authors["time_sync"], alone["time_sync"], rtol=0.05)
    with pytest.raises(InputError, match="base source 'calibration'"):
        authors_source_norms_mm(obs, model, base="calibration")


@pytest.fixture(scope="module")
def real_tracks():
    """The three prism excerpts, all five sources, both engines (world = station 1)."""
    weather = read_weather_eccc(DATA / "weather_ECCC_raw_excerpt.csv")
    calib = calibrate(read_gcp_rts_project(DATA / "GCP.txt"), samples=2000,
                      rng=np.random.default_rng(0))
    model = NoiseModel(TRIMBLE_S7)
    out = {}
    for k in ("1", "2", "3"):
        obs = read_prism_file(DATA / f"prism{k}.csv", station=k, prism=k,
                              additive_constant=0.01)
        kw = dict(T_world_station=calib.transforms[k], weather=weather)
        out[k] = (
            propagate(obs, model, **kw),
            propagate(obs, model, engine="mc", samples=2000, rng=np.random.default_rng(int(k)),
                      **kw),
        )
    return out


def test_real_excerpt_per_source_analysis(real_tracks):
    for k, (lin, mc) in real_tracks.items():
        assert 3.0 < lin.range_m.min() and lin.range_m.max() < 90.0  # SOURCE.md
        s_lin, s_mc = summarize_sources(lin), summarize_sources(mc)
        for s in s_lin:
            # both engines give the same table (Monte Carlo error of 2000 samples: ~3 %)
            np.testing.assert_allclose(s_mc[s].overall_median, s_lin[s].overall_median,
                                       rtol=0.04, atol=1e-3, err_msg=f"{k} {s}")
        for summary in (s_lin, s_mc):
            inst = summary["instrument"]
            # near the paper's 2.1 mm: (4 mm + 2 ppm) / 2 at 3-90 m is 2.0-2.1 mm
            assert 1.95 < inst.overall_median < 2.15, (k, inst.overall_median)
            assert inst.count[2] == 0 and inst.count.sum() == len(lin)
            assert 1.95 < inst.median[0] < 2.1 and 2.0 < inst.median[1] < 2.2
            # the paper's order: tilt and atmosphere a few hundredths of a mm at these ranges,
            # time synchronisation (the robot drives at ~1 m/s) and calibration around 1 mm
            assert summary["tilt"].overall_median < 0.05
            assert summary["atmosphere"].overall_median < 0.06
            assert 1.0 < summary["time_sync"].overall_median < 1.7
            if k == "1":  # the reference station: its transform is the identity
                assert summary["calibration"].overall_median == 0.0
            else:
                assert 0.6 < summary["calibration"].overall_median < 1.2
            assert summary["total"].overall_median > inst.overall_median
