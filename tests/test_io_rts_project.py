"""Readers and writers of the RTS_project formats (prism files, GCP.txt) and the native GCP CSV."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest

from _paths import EXCERPT as DATA
from rtsgt.errors import InputError
from rtsgt.io import rts_project
from rtsgt.io.gcp_csv import detect_gcp_format, read_gcp_csv, read_gcp_shots, write_gcp_csv
from rtsgt.io.rts_project import (
    read_gcp_rts_project,
    read_prism_file,
    write_gcp_rts_project,
    write_prism_file,
)
from rtsgt.measurement.polar import polar_to_cartesian
from rtsgt.types import GcpShots, Observations

GCP_HEADER = (
    "theodolite_number , marker_number , status , elevation , azimuth , distance , sec , nsec\n"
)


def real(name: str) -> Path:
    return DATA / name


def write(tmp_path: Path, text: str, name: str = "f.txt") -> Path:
    p = tmp_path / name
    p.write_text(text, encoding="utf-8")
    return p


# ---------------------------------------------------------------- real data


@pytest.mark.parametrize(
    "k, n, t0, t1", [(1, 215, 1668095037.077, 1668095169.076),
                     (2, 216, 1668095037.106, 1668095167.909),
                     (3, 214, 1668095037.568, 1668095168.768)],
)
def test_real_prism_files_match_source_md(k, n, t0, t1):
    obs = read_prism_file(real(f"prism{k}.csv"), station=k, prism=k)
    assert len(obs) == n  # line counts of SOURCE.md
    assert obs.t[0] == pytest.approx(t0, abs=1e-3)
    assert obs.t[-1] == pytest.approx(t1, abs=1e-3)
    assert obs.station == str(k) and obs.prism == str(k)
    assert obs.additive_constant == 0.01
    np.testing.assert_array_equal(obs.distance, obs.d + 0.01)
    assert np.all(obs.status == 0)
    # the robot starts 3-5 m from the stations and drives away to ~90 m
    assert 3.0 < obs.distance[0] < 5.0
    assert 85.0 < obs.distance.max() < 95.0
    # all zenith angles near the horizon, i.e. V really is the third column (not Hz)
    assert np.all(np.abs(obs.v - np.pi / 2) < 0.2)


def test_real_prism_column_order_is_t_d_v_hz():
    obs = read_prism_file(real("prism1.csv"), station=1, prism=1)
    # first line: 1668095037.0769036 3.18032819539402 1.502365743112384 0.9359011545999866
    assert obs.t[0] == 1668095037.0769036
    assert obs.d[0] == 3.18032819539402
    assert obs.v[0] == 1.502365743112384
    assert obs.hz[0] == 0.9359011545999866
    x, y, z = polar_to_cartesian(obs.hz[0], obs.v[0], obs.distance[0])
    assert z == pytest.approx(3.19032819539402 * np.cos(1.502365743112384))
    assert np.hypot(x, y) == pytest.approx(3.19032819539402 * np.sin(1.502365743112384))


def test_real_gcp_file():
    shots = read_gcp_rts_project(real("GCP.txt"))
    assert len(shots) == 36
    assert sorted(set(shots.station)) == ["1", "2", "3"]
    for s in "123":
        assert sorted(shots.marker[shots.station == s], key=int) == [str(m) for m in range(1, 13)]
    assert np.all(shots.status == 0)
    assert shots.additive_constant == 0.01
    np.testing.assert_array_equal(shots.lines, np.arange(2, 38))
    # "elevation" is the zenith angle: first row 1 , 1 , 0 , 1.5627 , 4.59018 , 4.70579
    assert (shots.v[0], shots.hz[0], shots.d[0]) == (1.5627, 4.59018, 4.70579)
    # nsec is not zero-padded: 1119001 -> 0.001119001 s, 480772 -> 0.000480772 s
    i = np.flatnonzero((shots.station == "2") & (shots.marker == "1"))[0]
    assert shots.t[i] - 1666982693 == pytest.approx(0.001119001, abs=1e-6)
    i = np.flatnonzero((shots.station == "2") & (shots.marker == "4"))[0]
    assert shots.t[i] - 1666982829 == pytest.approx(0.000480772, abs=1e-6)
    # station 1's clock was months off (July 2022), the others in late October 2022
    assert np.all(shots.t[shots.station == "1"] < 1.6575e9)
    assert np.all(shots.t[shots.station != "1"] > 1.6669e9)


def test_real_gcp_additive_constant_is_explicit():
    a = read_gcp_rts_project(real("GCP.txt"), additive_constant=0.0)
    b = read_gcp_rts_project(real("GCP.txt"))
    np.testing.assert_array_equal(a.d, b.d)
    np.testing.assert_allclose(b.distance - a.distance, 0.01, atol=1e-12)


# ---------------------------------------------------------------- round trips


def random_obs(rng, n=200) -> Observations:
    return Observations(
        t=1.6e9 + np.cumsum(rng.uniform(0.01, 1.0, n)), hz=rng.uniform(0, 2 * np.pi, n),
        v=rng.uniform(0.1, 3.0, n), d=rng.uniform(0.5, 800.0, n), station="2", prism="p",
        additive_constant=0.0344,
    )


def test_prism_round_trip_random(tmp_path):
    obs = random_obs(np.random.default_rng(1))
    p = tmp_path / "prism.csv"
    write_prism_file(p, obs)
    back = read_prism_file(p, station="2", prism="p", additive_constant=0.0344)
    for name in ("t", "hz", "v", "d", "status"):
        np.testing.assert_array_equal(getattr(back, name), getattr(obs, name))
    assert back.additive_constant == obs.additive_constant


def test_prism_round_trip_real_file_is_byte_identical(tmp_path):
    src = real("prism2.csv")
    obs = read_prism_file(src, station=2, prism=2)
    out = tmp_path / "prism2.csv"
    write_prism_file(out, obs)
    assert out.read_text() == src.read_text()


def test_gcp_round_trip_real(tmp_path):
    shots = read_gcp_rts_project(real("GCP.txt"))
    out = tmp_path / "GCP.txt"
    write_gcp_rts_project(out, shots)
    back = read_gcp_rts_project(out)
    for name in ("station", "marker", "hz", "v", "d", "t", "status", "lines"):
        np.testing.assert_array_equal(getattr(back, name), getattr(shots, name))


def random_shots(rng, n=50) -> GcpShots:
    return GcpShots(
        station=rng.integers(1, 4, n).astype(str), marker=np.arange(n).astype(str),
        hz=rng.uniform(0, 2 * np.pi, n), v=rng.uniform(0.2, 2.9, n), d=rng.uniform(1, 500, n),
        t=1.6e9 + rng.uniform(0, 1e7, n), status=rng.choice([0, 0, 0, 5], n),
        additive_constant=0.01,
    )


def test_gcp_round_trip_random_including_bad_status(tmp_path):
    shots = random_shots(np.random.default_rng(2))
    for writer, reader in ((write_gcp_rts_project, read_gcp_rts_project),
                           (write_gcp_csv, read_gcp_csv)):
        out = tmp_path / f"gcp_{writer.__name__}.txt"
        writer(out, shots)
        back = reader(out, additive_constant=0.01)
        for name in ("station", "marker", "hz", "v", "d", "t", "status"):
            np.testing.assert_array_equal(getattr(back, name), getattr(shots, name), err_msg=name)


def test_gcp_csv_and_rts_project_agree_and_auto_detect(tmp_path):
    shots = read_gcp_rts_project(real("GCP.txt"))
    out = tmp_path / "gcp.csv"
    write_gcp_csv(out, shots)
    assert out.read_text().splitlines()[0] == "station,marker,hz_rad,v_rad,d_m,t_s,status"
    assert detect_gcp_format(out) == "csv"
    assert detect_gcp_format(real("GCP.txt")) == "rts-project"
    a = read_gcp_shots(out, additive_constant=0.01)
    b = read_gcp_shots(real("GCP.txt"))
    for name in ("station", "marker", "hz", "v", "d", "t"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name))
    assert read_gcp_shots(out).additive_constant == 0.0  # csv default: no constant
    with pytest.raises(InputError, match="unknown GCP format"):
        read_gcp_shots(out, format="leica")


def test_gcp_csv_units_optional_columns_quotes_and_comments(tmp_path):
    p = write(tmp_path, (
        "# shots of 2024-05-01\n"
        "marker,station,v_deg,hz_gon,d_m\n"
        "\n"
        '"A 1",S1,90,100,10.5\n'
        "B,S1,45,200,3\n"
    ), "g.csv")
    shots = read_gcp_csv(p, additive_constant=0.02)
    assert list(shots.marker) == ["A 1", "B"] and list(shots.station) == ["S1", "S1"]
    np.testing.assert_allclose(shots.v, [np.pi / 2, np.pi / 4])
    np.testing.assert_allclose(shots.hz, [np.pi / 2, np.pi])
    np.testing.assert_array_equal(shots.lines, [4, 5])
    assert np.all(np.isnan(shots.t)) and np.all(shots.status == 0)
    np.testing.assert_allclose(shots.distance, [10.52, 3.02])


def test_writers_are_atomic(tmp_path, monkeypatch):
    obs = random_obs(np.random.default_rng(3), 10)
    p = tmp_path / "prism.csv"
    p.write_text("old content\n")

    def boom(src, dst):
        raise OSError("disk full")

    monkeypatch.setattr(os, "replace", boom)
    with pytest.raises(OSError, match="disk full"):
        write_prism_file(p, obs)
    assert p.read_text() == "old content\n"
    assert sorted(x.name for x in tmp_path.iterdir()) == ["prism.csv"]  # no temporary left


def test_writers_refuse_what_cannot_be_read_back(tmp_path):
    obs = random_obs(np.random.default_rng(4), 5)
    bad = Observations(obs.t, obs.hz, obs.v, obs.d, status=[0, 0, 3, 0, 0])
    p = tmp_path / "x.csv"
    with pytest.raises(ValueError, match="status"):
        write_prism_file(p, bad)
    with pytest.raises(ValueError, match="finite"):
        write_prism_file(p, Observations(obs.t, obs.hz, obs.v, np.full(5, np.nan)))
    shots = random_shots(np.random.default_rng(5), 4)
    with pytest.raises(ValueError, match="finite shot times"):
        write_gcp_rts_project(p, GcpShots(shots.station, shots.marker, shots.hz, shots.v, shots.d))
    with pytest.raises(ValueError, match="commas or spaces"):
        write_gcp_rts_project(
            p, GcpShots(["a b"] * 4, shots.marker, shots.hz, shots.v, shots.d, shots.t)
        )
    assert not p.exists()


def test_sec_nsec_split_reads_back_exactly():
    rng = np.random.default_rng(6)
    t = np.concatenate([1.6e9 + rng.uniform(0, 1e8, 10000), [1.6e9 + 1 - 1e-10, 5.0]])
    sec, nsec = rts_project._sec_nsec(t)
    assert np.all((nsec >= 0) & (nsec < 1_000_000_000))
    np.testing.assert_array_equal(sec.astype(float) + nsec.astype(float) * 1e-9, t)


# ---------------------------------------------------------------- bad input

PRISM_OK = "1.0 10.0 1.5 0.3\n2.0 10.1 1.5 0.3\n3.0 10.2 1.5 0.3\n"


@pytest.mark.parametrize(
    "text, line, pattern",
    [
        ("1.0 10.0 1.5 0.3\n2.0 10.1 1.5\n", 2, r"expected 4 whitespace-separated columns"),
        ("1.0 10.0 1.5 0.3 7\n", 1, r"expected 4 .* got 5"),
        ("1.0 10.0 1.5 0.3\n2.0 abc 1.5 0.3\n", 2, r"number in column 'd', got 'abc'"),
        ("1.0 10.0 1.5 0.3\n2.0 nan 1.5 0.3\n", 2, r"finite number in column 'd', got 'nan'"),
        ("1.0 10.0 1.5 0.3\n2.0 10 1.5 inf\n", 2, r"finite number in column 'Hz'"),
        ("1.0 10.0 1.5 0.3\n2.0 -0.5 1.5 0.3\n", 2, r"positive slope distance, got -0.5"),
        ("1.0 10.0 1.5 0.3\n2.0 10.0 0.0 0.3\n", 2, r"zenith angle in \(0, pi\) rad, got 0.0"),
        ("1.0 10.0 3.2 0.3\n", 1, r"zenith angle .* got 3.2"),
        ("1.0 10.0 1.5 0.3\n\n1.0 10.0 1.5 0.3\n", 3, r"duplicated timestamp .* remove the dup"),
        ("1.0 10.0 1.5 0.3\n3.0 10.0 1.5 0.3\n2.0 10.0 1.5 0.3\n", 3, r"earlier .* sort the file"),
    ],
)
def test_prism_bad_input_names_file_and_line(tmp_path, text, line, pattern):
    p = write(tmp_path, text, "prism9.csv")
    with pytest.raises(InputError, match=pattern) as info:
        read_prism_file(p, station=1, prism=1)
    assert info.value.path == str(p) and info.value.line == line
    assert str(info.value).startswith(f"{p}:{line}: ")


def test_prism_empty_and_missing_files(tmp_path):
    p = write(tmp_path, "\n  \n# only a comment\n")
    with pytest.raises(InputError, match="empty file") as info:
        read_prism_file(p, station=1, prism=1)
    assert str(p) in str(info.value)
    with pytest.raises(InputError, match="file not found"):
        read_prism_file(tmp_path / "nope.csv", station=1, prism=1)
    with pytest.raises(InputError, match="directory"):
        read_prism_file(tmp_path, station=1, prism=1)
    with pytest.raises(InputError, match="additive constant"):
        read_prism_file(write(tmp_path, PRISM_OK), station=1, prism=1, additive_constant=np.nan)


ROW = "1 , 1 , 0 , 1.5627 , 4.59018 , 4.70579 , 1657288500 , 324114793\n"


@pytest.mark.parametrize(
    "body, line, pattern",
    [
        ("1 , 2 , 0 , 1.5 , 4.5 , 4.7 , 1657288500\n", 3, r"expected 8 ,-separated columns"),
        ("1 , 2 , 0 , 1.5 , 4.5 , x4.7 , 1657288500 , 3\n", 3, r"column 'distance', got 'x4.7'"),
        ("1 , 2 , ok , 1.5 , 4.5 , 4.7 , 1657288500 , 3\n", 3, r"integer in column 'status'"),
        ("1 , 2 , 0 , 1.5 , 4.5 , 4.7 , 1657288500.5 , 3\n", 3, r"integer in column 'sec'"),
        ("1 , 2 , 0 , 1.5 , 4.5 , 4.7 , 1657288500 , 1000000000\n", 3, r"nsec in \[0, 999999999\]"),
        ("1 , 2 , 0 , nan , 4.5 , 4.7 , 1657288500 , 3\n", 3, r"finite number .*'elevation'"),
        ("1 , 2 , 0 , 1.5 , 4.5 , -4.7 , 1657288500 , 3\n", 3, r"positive slope distance"),
        ("1 , 2 , 0 , 3.5 , 4.5 , 4.7 , 1657288500 , 3\n", 3, r"zenith angle in \(0, pi\)"),
        (" , 2 , 0 , 1.5 , 4.5 , 4.7 , 1657288500 , 3\n", 3, r"empty theodolite_number"),
    ],
)
def test_gcp_bad_rows_name_file_and_line(tmp_path, body, line, pattern):
    p = write(tmp_path, GCP_HEADER + ROW + body, "GCP.txt")
    with pytest.raises(InputError, match=pattern) as info:
        read_gcp_rts_project(p)
    assert info.value.path == str(p) and info.value.line == line


def test_gcp_invalid_shots_may_hold_garbage(tmp_path):
    # a failed shot (status != 0) with a zero distance and NaN angle is kept, not refused
    p = write(tmp_path, GCP_HEADER + ROW + "1 , 2 , 7 , nan , 4.5 , 0 , 1657288500 , 3\n")
    shots = read_gcp_rts_project(p)
    assert list(shots.status) == [0, 7]


def test_gcp_header_and_empty_files(tmp_path):
    with pytest.raises(InputError, match="expected the header") as info:
        read_gcp_rts_project(write(tmp_path, ROW))
    assert info.value.line == 1
    with pytest.raises(InputError, match="no GCP shot after the header"):
        read_gcp_rts_project(write(tmp_path, GCP_HEADER))
    with pytest.raises(InputError, match="empty file"):
        read_gcp_rts_project(write(tmp_path, ""))


@pytest.mark.parametrize(
    "text, line, pattern",
    [
        ("station,marker,hz_rad,d_m\n1,1,0.5,3\n", 1, r"exactly one column v_rad or v_deg"),
        ("station,marker,hz_rad,hz_deg,v_rad,d_m\n", 1, r"found hz_rad, hz_deg"),
        ("station,hz_rad,v_rad,d_m\n1,0.5,1.5,3\n", 1, r"missing column\(s\) marker"),
        ("station,marker,hz_rad,v_rad,d_m\n1,1,0.5,1.5\n", 2, r"expected 5 comma-separated"),
        ("station,marker,hz_rad,v_rad,d_m\n1,1,0.5,1.5,-3\n", 2, r"positive slope distance"),
        ("station,marker,hz_rad,v_rad,d_m\n1,,0.5,1.5,3\n", 2, r"empty marker"),
        ("station,marker,hz_rad,v_rad,d_m,t_s\n1,1,0.5,1.5,3,nan\n", 2, r"finite number .*t_s"),
        ("station,marker,hz_rad,v_rad,d_m\n", None, r"no GCP shot after the header"),
        ("", None, r"empty file"),
    ],
)
def test_gcp_csv_bad_input(tmp_path, text, line, pattern):
    p = write(tmp_path, text, "g.csv")
    with pytest.raises(InputError, match=pattern) as info:
        read_gcp_csv(p)
    assert info.value.path == str(p) and info.value.line == line


# ---------------------------------------------------------------- times that are not seconds

NS = "1668095037077000000"  # 2022-11-10 15:43:57.077 UTC in nanoseconds
TRACK_HEAD = "t,x,y,z,cov_xx,cov_xy,cov_xz,cov_yy,cov_yz,cov_zz\n"
TRACK_ROW = ",1,2,3,1e-6,0,0,1e-6,0,1e-6\n"


def _read_track(p):
    from rtsgt.io.track_csv import read_track_csv

    return read_track_csv(p)


def _read_weather(p):
    from rtsgt.io.weather import read_weather_csv

    return read_weather_csv(p)


def _read_query_times(p):
    from rtsgt.io.track_csv import read_query_times

    return read_query_times(p)


@pytest.mark.parametrize(
    "reader, text, line, unit",
    [
        (lambda p: read_prism_file(p, station=1, prism=1),
         f"1668095036.5 10.0 1.5 0.3\n{NS} 10.0 1.5 0.3\n", 2, "nanoseconds"),
        (lambda p: read_prism_file(p, station=1, prism=1),
         "# ms\n1668095037077 10.0 1.5 0.3\n", 2, "milliseconds"),
        (read_gcp_rts_project,
         GCP_HEADER + f"1 , 1 , 0 , 1.5627 , 4.59018 , 4.70579 , {NS} , 0\n", 2, "nanoseconds"),
        (read_gcp_csv, f"station,marker,hz_rad,v_rad,d_m,t_s\n1,1,0.5,1.5,3,\n1,2,0.5,1.5,3,{NS}\n",
         3, "nanoseconds"),
        (_read_track, TRACK_HEAD + "1668095036" + TRACK_ROW + NS + TRACK_ROW, 3, "nanoseconds"),
        (_read_weather, f"t_s,temperature_c,pressure_hpa,humidity_pct\n{NS},2,937,90\n", 2,
         "nanoseconds"),
        (_read_query_times, "1668095037077000\n", 1, "microseconds"),
    ],
)
def test_times_that_look_like_nanoseconds_are_refused(tmp_path, reader, text, line, unit):
    """Every reader of measurement times refuses times far beyond any Unix time in seconds
    (>= 1e11 s, the year 5138), saying which unit they look like and what to do."""
    p = write(tmp_path, text, "times.csv")
    with pytest.raises(InputError, match=rf"looks like {unit} .* seconds") as info:
        reader(p)
    assert info.value.path == str(p) and info.value.line == line
    assert "2022-11-10 15:43:57" in str(info.value)


def test_unix_seconds_and_relative_seconds_are_accepted(tmp_path):
    for t0 in ("0.0", "1668095037.077", "99999999999"):
        obs = read_prism_file(write(tmp_path, f"{t0} 10.0 1.5 0.3\n"), station=1, prism=1)
        assert obs.t[0] == float(t0)
