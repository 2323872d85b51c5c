"""Filtering modules 1 and 2 (Vaidis et al. 2022): rtsgt.filtering.modules.

Hand-built cases with known answers, and random cases against straightforward sequential
reference implementations written here from the rules of the module docstring.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from _paths import EXAMPLE_TOML, EXCERPT
from rtsgt.errors import ConfigError, InputError
from rtsgt.filtering import (
    MODULE1_REASONS,
    MODULE2_REASONS,
    FilterParams,
    FilterReport,
    module1,
    module2,
)
from rtsgt.filtering.modules import ANCHOR_NEIGHBOURS, DEFAULT_MAX_DISTANCE_M
from rtsgt.io.config import load_config
from rtsgt.io.rts_project import read_prism_file
from rtsgt.types import Observations, PrismTrack

TWO_PI = 2.0 * math.pi
P = FilterParams()


# --------------------------------------------------------------------------------------------
# References
# --------------------------------------------------------------------------------------------


def ref_module1(t, hz, v, d, status, p: FilterParams):
    """Module 1, one measurement at a time: a reason per measurement ("" = kept), blocks."""
    n = len(t)
    reason = [""] * n
    for i in range(n):
        finite = all(math.isfinite(x) for x in (t[i], hz[i], v[i], d[i]))
        if status[i] != 0:
            reason[i] = "status"
        elif not finite:
            reason[i] = "non_finite"
        elif d[i] > p.max_distance:
            reason[i] = "max_distance"
    prev_t = None
    for i in range(n):
        if reason[i]:
            continue
        if prev_t is not None and t[i] == prev_t:
            reason[i] = "duplicate_time"
        prev_t = t[i]

    def gate(i, j):  # reason of comparing j with i ("" = passes)
        dt = abs(t[j] - t[i])
        dhz = abs(math.remainder(hz[j] - hz[i], TWO_PI))
        if abs(d[j] - d[i]) / dt > p.tau_r:
            return "rate_distance"
        if dhz / dt > p.tau_a:
            return "rate_hz"
        if abs(v[j] - v[i]) / dt > p.tau_e:
            return "rate_v"
        return ""

    blocks = []  # the measurements still in the series, split at the gaps
    for i in range(n):
        if reason[i]:
            continue
        if not blocks or t[i] - t[blocks[-1][-1]] > p.tau_s:
            blocks.append([])
        blocks[-1].append(i)
    for block in blocks:
        # the anchor: the first that agrees with one of its next 3 (judged with 2 or more)
        a = 0
        while len(block) - a - 1 >= 2:
            nxt = block[a + 1:a + 4]
            if any(gate(block[a], j) == "" for j in nxt):
                break
            reason[block[a]] = gate(block[a], nxt[0])
            a += 1
        last = block[a]  # last accepted measurement of the block
        for i in block[a + 1:]:
            reason[i] = gate(last, i)
            if not reason[i]:
                last = i
    return reason, len(blocks)


def ref_module2(times, p: FilterParams):
    """Module 2 by brute force: kept intervals, kept masks and reasons per series."""
    segments = []
    for t in times:
        segs, start = [], 0
        for i in range(1, len(t) + 1):
            if i == len(t) or t[i] - t[i - 1] > p.tau_s:
                if len(t):
                    segs.append((t[start], t[i - 1]))
                start = i
        segments.append(segs)
    cuts = sorted({x for segs in segments for s in segs for x in s})
    covered = []
    for a, b in zip(cuts[:-1], cuts[1:], strict=True):
        mid = 0.5 * (a + b)
        if all(any(s0 <= mid <= s1 for s0, s1 in segs) for segs in segments):
            if covered and covered[-1][1] == a:
                covered[-1] = (covered[-1][0], b)
            else:
                covered.append((a, b))
    kept_iv = [(a, b) for a, b in covered if b - a >= p.tau_l]
    short_iv = [(a, b) for a, b in covered if b - a < p.tau_l]
    masks, reasons = [], []
    for t in times:
        keep = [any(a <= x <= b for a, b in kept_iv) for x in t]
        for a, b in kept_iv:
            before = [i for i, x in enumerate(t) if x <= a]
            after = [i for i, x in enumerate(t) if x >= b]
            keep[before[-1]] = True
            keep[after[0]] = True
        why = []
        for x, k in zip(t, keep, strict=True):
            if k:
                why.append("")
            elif any(a <= x <= b for a, b in short_iv):
                why.append("short_interval")
            else:
                why.append("not_all_tracked")
        masks.append(np.array(keep, dtype=bool))
        reasons.append(why)
    return np.array(kept_iv, dtype=float).reshape(-1, 2), masks, reasons


def counts(reasons, names):
    return {r: sum(1 for x in reasons if x == r) for r in names}


# --------------------------------------------------------------------------------------------
# Helpers
# --------------------------------------------------------------------------------------------


def obs(t, hz=None, v=None, d=None, status=None, **kw):
    t = np.asarray(t, dtype=float)
    n = t.size
    hz = np.full(n, 1.0) if hz is None else hz
    v = np.full(n, 1.5) if v is None else v
    d = np.full(n, 20.0) if d is None else d
    return Observations(t, np.asarray(hz, float), np.asarray(v, float), np.asarray(d, float),
                        status, **kw)


def assert_module1_matches_reference(o, p=P):
    kept, rep = module1(o, p)
    ref, blocks = ref_module1(o.t.tolist(), o.hz.tolist(), o.v.tolist(), o.distance.tolist(),
                              o.status.tolist(), p)
    keep = np.array([r == "" for r in ref])
    np.testing.assert_array_equal(kept.t, o.t[keep])
    np.testing.assert_array_equal(kept.hz, o.hz[keep])
    np.testing.assert_array_equal(kept.d, o.d[keep])
    assert dict(rep.removed) == counts(ref, MODULE1_REASONS)
    assert rep.n_in == len(o) and rep.n_kept == int(keep.sum())
    assert rep.n_removed == len(o) - int(keep.sum())
    assert rep.n_blocks == blocks
    assert rep.per_series == (dict(rep.removed),)
    # the mask of what was kept and the reason of each removal, indexed like the input
    (mask,), (why,) = rep.kept_masks, rep.reasons
    np.testing.assert_array_equal(mask, keep)
    assert why.tolist() == ref
    assert_masks_reproduce_counts(rep, [o], kept=[kept], names=MODULE1_REASONS)
    return kept, rep, ref


def assert_masks_reproduce_counts(rep, series, kept, names):
    """A report's masks and reasons say what its counts and its kept series say."""
    assert len(rep.kept_masks) == len(rep.reasons) == len(series) == len(rep.per_series)
    for s, k, mask, why, c in zip(series, kept, rep.kept_masks, rep.reasons, rep.per_series,
                                  strict=True):
        assert mask.dtype == bool and mask.shape == why.shape == (len(s),)
        assert not mask.flags.writeable and not why.flags.writeable
        np.testing.assert_array_equal(k.t, s.t[mask])
        np.testing.assert_array_equal(why == "", mask)
        assert set(why[~mask].tolist()) <= set(names)
        assert {r: int(np.sum(why == r)) for r in names} == dict(c)
    assert rep.n_kept == sum(int(m.sum()) for m in rep.kept_masks)
    # summary.json holds the counts only, as before the masks existed
    assert rep.as_dict() == {"module": rep.module, "n_in": rep.n_in, "n_kept": rep.n_kept,
                             "removed": dict(rep.removed),
                             "per_series": [dict(c) for c in rep.per_series],
                             "n_blocks": rep.n_blocks}


def random_observations(rng, n, *, outliers=0.05, bursts=2, gaps=2):
    """A realistic station series: a prism moving at up to ~1.5 m/s at 5-50 m, measured every
    0.3-0.5 s, the horizontal direction crossing 0 / 2 pi, gaps, outliers, bursts of
    outliers, invalid statuses, NaNs and duplicated times."""
    dt = rng.uniform(0.3, 0.5, n - 1)
    dt[rng.integers(0, n - 1, gaps)] += rng.uniform(2.0, 6.0, gaps)  # some over tau_s
    t = 1.668e9 + np.concatenate([[0.0], np.cumsum(dt)])
    dup = rng.random(n) < 0.01
    dup[0] = False
    t[dup] = t[np.flatnonzero(dup) - 1]
    rate = rng.uniform(-0.8, 0.8) * P.tau_a  # inside the gate, crossing zero
    hz = np.mod(rng.uniform(-0.05, 0.05) + rate * (t - t[0]) + 1e-4 * rng.normal(size=n),
                TWO_PI)
    v = 1.5 + 0.5 * P.tau_e * np.sin(0.05 * (t - t[0])) + 1e-5 * rng.normal(size=n)
    d = 20.0 + 10.0 * np.sin(0.03 * (t - t[0])) + 1e-3 * rng.normal(size=n)
    bad = rng.random(n) < outliers
    for _ in range(bursts):
        s = int(rng.integers(0, n))
        bad[s:s + int(rng.integers(2, 100))] = True
    which = rng.integers(0, 3, n)
    jump = rng.choice([-1, 1], n) * rng.uniform(0.05, 3.0, n)
    d = np.where(bad & (which == 0), d + 5 * jump, d)
    hz = np.where(bad & (which == 1), np.mod(hz + 0.1 * jump, TWO_PI), hz)
    v = np.where(bad & (which == 2), v + 0.1 * jump, v)
    status = np.where(rng.random(n) < 0.02, rng.integers(1, 5, n), 0)
    hz[rng.random(n) < 0.01] = np.nan
    wild = rng.random(n) < outliers / 5  # wild shots: beyond the largest distance, or not
    d = np.where(wild, rng.choice([234.5, 1234.5], n), d)
    return Observations(t, hz, v, d, status, station="2", prism="2", additive_constant=0.01)


# --------------------------------------------------------------------------------------------
# Module 1: hand-built cases
# --------------------------------------------------------------------------------------------


def test_parameters_of_the_paper():
    assert (P.tau_r, P.tau_s, P.tau_l) == (2.0, 3.0, 2.0)
    assert P.tau_a == pytest.approx(math.radians(1.0)) and P.tau_e == pytest.approx(P.tau_a)
    q = FilterParams.from_degrees(tau_a_deg=2.0, tau_e_deg=0.5)
    assert q.tau_a == pytest.approx(math.radians(2.0)) and q.tau_e == pytest.approx(
        math.radians(0.5))
    for bad in ({"tau_r": 0.0}, {"tau_a": -1.0}, {"tau_s": np.nan}, {"tau_l": -1.0}):
        with pytest.raises(InputError):
            FilterParams(**bad)


def test_one_outlier_removes_one_measurement():
    t = np.arange(6) * 0.5
    d = np.array([10.0, 10.1, 14.0, 10.2, 10.3, 10.4])  # 8 m/s jump at index 2
    kept, rep = module1(obs(t, d=d))
    np.testing.assert_array_equal(kept.t, t[[0, 1, 3, 4, 5]])
    assert rep.removed["rate_distance"] == 1 and rep.n_removed == 1
    assert rep.summary() == "module1: kept 5/6 (rate_distance 1)"
    # the successor was compared with the last accepted (index 1), not with the outlier
    assert_module1_matches_reference(obs(t, d=d))


def test_horizontal_direction_is_unwrapped_across_zero():
    t = np.arange(5) * 1.0
    step = 0.5 * P.tau_a  # rad per second, inside the gate
    up = np.mod(TWO_PI - 2.2 * step + step * t, TWO_PI)  # 2pi - eps ... crosses to small values
    assert up[3] < 1.0 < up[2]
    kept, rep = module1(obs(t, hz=up))
    assert len(kept) == 5 and rep.n_removed == 0
    down = np.mod(2.2 * step - step * t, TWO_PI)  # crosses 0 going down
    assert down[2] < 1.0 < down[3]
    kept, rep = module1(obs(t, hz=down))
    assert len(kept) == 5
    # a genuine jump of half a turn is still a jump
    jump = up.copy()
    jump[2] = np.mod(jump[2] + math.pi, TWO_PI)
    kept, rep = module1(obs(t, hz=jump))
    assert rep.removed["rate_hz"] == 1
    np.testing.assert_array_equal(kept.t, t[[0, 1, 3, 4]])


def test_rate_equal_to_the_threshold_passes():
    t = np.array([0.0, 0.5, 1.0, 1.5])
    d = np.array([0.0, 1.0, 2.0, 3.0 + 2.0**-20])  # exactly 2 m/s, then just over
    kept, rep = module1(obs(t, d=d + 10.0))
    np.testing.assert_array_equal(kept.t, t[:3])
    assert rep.removed["rate_distance"] == 1
    tau = 2.0**-6  # rad/s, exactly representable
    p = FilterParams(tau_a=tau, tau_e=tau)
    hz = np.array([1.0, 1.0 + tau * 0.5, 1.0 + tau * 1.0, 1.0 + tau * 1.5 + 2.0**-30])
    kept, rep = module1(obs(t, hz=hz), p)
    assert rep.removed["rate_hz"] == 1 and len(kept) == 3
    kept, rep = module1(obs(t, v=hz), p)
    assert rep.removed["rate_v"] == 1 and len(kept) == 3


def test_reasons_are_tested_in_order_and_counted():
    t = np.arange(8) * 0.5
    d = np.full(8, 20.0)
    hz = np.full(8, 1.0)
    v = np.full(8, 1.5)
    d[1] += 5.0
    hz[1] += 0.1  # fails distance and hz: counted as distance
    hz[3] += 0.1
    v[3] += 0.1  # fails hz and v: counted as hz
    v[5] += 0.1
    status = np.array([0, 0, 0, 0, 0, 0, 3, 0])
    o = obs(t, hz=hz, v=v, d=d, status=status)
    kept, rep = module1(o)
    assert dict(rep.removed) == {"status": 1, "non_finite": 0, "max_distance": 0,
                                 "duplicate_time": 0, "rate_distance": 1, "rate_hz": 1,
                                 "rate_v": 1}
    assert list(rep.removed) == list(MODULE1_REASONS)
    np.testing.assert_array_equal(kept.t, t[[0, 2, 4, 7]])
    assert rep.summary() == "module1: kept 4/8 (status 1, rate_distance 1, rate_hz 1, rate_v 1)"
    assert_module1_matches_reference(o)


def test_invalid_statuses_nans_and_duplicates_never_become_the_reference():
    t = np.array([0.0, 0.4, 0.8, 0.8, 1.2, 1.6])
    d = np.array([20.0, 99.0, 20.1, 20.1, 20.2, np.nan])
    status = np.array([0, 7, 0, 0, 0, 0])
    o = obs(t, d=d, status=status)
    kept, rep = module1(o)
    np.testing.assert_array_equal(kept.t, [0.0, 0.8, 1.2])
    assert rep.removed["status"] == 1 and rep.removed["non_finite"] == 1
    assert rep.removed["duplicate_time"] == 1 and rep.n_kept == 3
    assert_module1_matches_reference(o)


def test_blocks_split_at_gaps_longer_than_tau_s_without_off_by_one():
    # block 1: 0 .. 1.2 (an outlier burst at its end), gap 5 s, block 2 starts far away,
    # then a gap of exactly tau_s (no split) with a jump over it that passes the rate gate
    t = np.array([0.0, 0.5, 1.0, 1.5, 6.5, 7.0, 10.0, 10.5])
    d = np.array([20.0, 20.1, 30.0, 31.0, 50.0, 50.2, 55.9, 56.0])
    o = obs(t, d=d)
    kept, rep = module1(o)
    # 30, 31: rejected against 20.1; 50: first of its block, accepted despite the jump;
    # 55.9 over 3.0 s from 50.2 = 1.9 m/s: passes (same block, the gap is not > tau_s)
    np.testing.assert_array_equal(kept.t, t[[0, 1, 4, 5, 6, 7]])
    assert rep.n_blocks == 2 and rep.removed["rate_distance"] == 2
    assert_module1_matches_reference(o)
    # a gap just over tau_s splits: the first measurement after it is not compared
    t2 = t.copy()
    t2[6:] += 1e-6
    d2 = d.copy()
    d2[6:] += 100.0
    kept, rep = module1(obs(t2, d=d2))
    assert rep.n_blocks == 3 and len(kept) == 6
    # the last measurement of a block is tested (it is not dropped or skipped)
    d3 = d.copy()
    d3[5] = 80.0
    kept, rep = module1(obs(t, d=d3))
    assert 7.0 not in kept.t and 10.0 in kept.t


def test_long_burst_of_outliers():
    """More rejections in a row than the vectorised search looks at first (64, 256, ...)."""
    n = 1200
    t = np.arange(n) * 0.4
    d = 20.0 + 0.01 * np.sin(t)
    d[100:500] += 500.0  # 400 in a row (over 2 m/s even across 160 s)
    d[700:] += 500.0  # never comes back before the end of the block: all rejected
    o = obs(t, d=d)
    kept, rep, _ = assert_module1_matches_reference(o)
    assert rep.removed["rate_distance"] == 400 + 500
    assert kept.t[-1] == t[699]


def test_a_wild_first_shot_of_a_block_costs_one_measurement():
    """The first measurement of a block is the reference only when it agrees with one of the
    next ones: a wild one (valid status, a plausible distance) is rejected alone."""
    t = np.arange(8) * 0.4
    d = 20.0 + 0.1 * t
    d[0] = 234.5  # under the largest distance: only the rate gates can tell
    kept, rep, _ = assert_module1_matches_reference(obs(t, d=d))
    np.testing.assert_array_equal(kept.t, t[1:])
    assert rep.removed["rate_distance"] == 1 and rep.reasons[0][0] == "rate_distance"
    # two wild shots that disagree with each other too: both go, the block stays
    d[1] = 5.0
    kept, rep, _ = assert_module1_matches_reference(obs(t, d=d))
    np.testing.assert_array_equal(kept.t, t[2:])
    # a good first measurement followed by an outlier stays the reference (the paper's rule)
    d = 20.0 + 0.1 * t
    d[1] = 234.5
    kept, _, _ = assert_module1_matches_reference(obs(t, d=d))
    np.testing.assert_array_equal(kept.t, t[[0, *range(2, 8)]])
    # with a single neighbour nothing tells which of the two is wrong: the first is kept
    kept, _, _ = assert_module1_matches_reference(obs(t[:2], d=np.array([234.5, 20.0])))
    np.testing.assert_array_equal(kept.d, [234.5])
    # the anchor is judged against at most ANCHOR_NEIGHBOURS followers: a good first
    # measurement followed by that many outliers is rejected
    d = 20.0 + 0.1 * t
    d[1:1 + ANCHOR_NEIGHBOURS] = 234.5 + np.arange(ANCHOR_NEIGHBOURS) * 50.0
    _, rep, _ = assert_module1_matches_reference(obs(t, d=d))
    assert rep.reasons[0][0] == "rate_distance"


def excerpt_with_wild_shots(distance: float) -> list[tuple[Observations, Observations]]:
    """Each station of the shipped excerpt, and the same with a valid shot of ``distance``
    0.2 s before the first measurement of each of its blocks (gaps > tau_s) but those of one
    measurement (a wild shot and one measurement disagree, and nothing tells which is wrong:
    the first is kept, as in the paper; module 2 drops a lone measurement anyway)."""
    out = []
    for i in (1, 2, 3):
        o = read_prism_file(EXCERPT / f"prism{i}.csv", station=i, prism=i)
        first = np.flatnonzero(np.diff(o.t, prepend=-np.inf) > P.tau_s)
        first = first[np.diff(first, append=len(o)) >= 2]
        wild = Observations(np.insert(o.t, first, o.t[first] - 0.2),
                            np.insert(o.hz, first, o.hz[first]), np.insert(o.v, first, o.v[first]),
                            np.insert(o.d, first, distance), station=o.station, prism=o.prism)
        out.append((o, wild))
    return out


@pytest.mark.parametrize("distance, max_distance", [(1234.5, None), (1234.5, 1e4),
                                                    (234.5, None)])
def test_wild_first_shots_on_the_excerpt_cost_no_good_measurement(distance, max_distance):
    """A valid shot of 1234.5 m (or one under the largest distance) before each block of the
    real excerpt is the only measurement removed: every good one is kept as without it (the
    first measurement used to be the block's reference, and the block was lost with it)."""
    p = P if max_distance is None else FilterParams(max_distance=max_distance)
    reason = "max_distance" if distance > p.max_distance else "rate_distance"
    for o, wild in excerpt_with_wild_shots(distance):
        kept, rep = module1(o, p)
        kept_w, rep_w = module1(wild, p)
        assert rep_w.n_blocks == rep.n_blocks == 4
        shots = wild.d == distance
        assert rep_w.reasons[0][shots].tolist() == [reason] * (3 + (o.station == "3"))
        np.testing.assert_array_equal(kept_w.t, kept.t)  # the same good measurements
        assert rep_w.n_kept == rep.n_kept > 200
        np.testing.assert_array_equal(rep_w.reasons[0][~shots], rep.reasons[0])


def test_largest_distance_option():
    """``max_distance`` removes longer raw distances (the reference code's 1000 m by default,
    ``[filter] max_distance_m``); a value that is not positive is refused naming the key."""
    assert P.max_distance == DEFAULT_MAX_DISTANCE_M == 1000.0
    t = np.arange(6) * 0.4
    d = np.array([20.0, 20.1, 1000.0, 1000.01, 20.2, 20.3])
    # the limit applies to the raw distance, without the additive constant; a distance equal
    # to it passes (then fails the rate gate)
    _, rep = module1(obs(t, d=d - 0.01, additive_constant=0.01), FilterParams(max_distance=999.99))
    np.testing.assert_array_equal(rep.reasons[0], ["", "", "rate_distance", "max_distance", "",
                                                   ""])
    _, rep = module1(obs(t, d=d))
    assert rep.removed["max_distance"] == 1
    _, rep = module1(obs(t, d=d), FilterParams(max_distance=1e4))
    assert rep.removed["max_distance"] == 0
    assert_module1_matches_reference(obs(t, d=d), FilterParams(max_distance=30.0))
    for bad in (0.0, -5.0, math.nan, math.inf):
        with pytest.raises(InputError, match=r"Expected a finite max_distance > 0 m"):
            FilterParams(max_distance=bad)


@pytest.mark.parametrize("value, ok", [("250.0", True), ("1e4", True), ("inf", False),
                                       ("0.0", False), ("-1", False), ('"far"', False)])
def test_largest_distance_key(tmp_path, value, ok):
    text = EXAMPLE_TOML.read_text(encoding="utf-8").replace('"data/', f'"{EXCERPT}/')
    path = tmp_path / "d.toml"
    assert text.count("[filter]\n") == 1
    path.write_text(text.replace("[filter]\n", f"[filter]\nmax_distance_m = {value}\n"),
                    encoding="utf-8")
    if ok:
        assert load_config(path).options.filter.max_distance == float(value)
        return
    with pytest.raises(ConfigError) as info:
        load_config(path)
    msg = str(info.value)
    assert len(msg.splitlines()) == 1 and str(path) in msg and "max_distance_m" in msg


def test_times_going_backwards_is_an_input_error():
    o = obs([0.0, 0.4, 0.3, 0.8], source="prism2.csv")
    with pytest.raises(InputError, match=r"^prism2.csv: Expected observations in time order, "
                       r"got t = 0.3 s after t = 0.4 s \(measurements 1 and 2\)$"):
        module1(o)
    with pytest.raises(InputError, match="Expected Observations"):
        module1(np.zeros(3))


def test_empty_and_single():
    kept, rep = module1(obs(np.empty(0)))
    assert len(kept) == 0 and rep.n_blocks == 0 and rep.n_in == 0
    kept, rep = module1(obs([1.0]))
    assert len(kept) == 1 and rep.n_blocks == 1


def test_additive_constant_and_metadata_carry_through():
    o = obs(np.arange(4) * 0.5, station="3", prism="3", additive_constant=0.01, source="x.csv")
    kept, _ = module1(o)
    assert (kept.station, kept.prism, kept.additive_constant, kept.source) == (
        "3", "3", 0.01, "x.csv")


# --------------------------------------------------------------------------------------------
# Module 1: random cases against the reference
# --------------------------------------------------------------------------------------------


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), n=st.integers(2, 600),
       outliers=st.sampled_from([0.0, 0.02, 0.2, 0.6]), bursts=st.integers(0, 4))
def test_module1_matches_the_sequential_reference(seed, n, outliers, bursts):
    o = random_observations(np.random.default_rng(seed), n, outliers=outliers, bursts=bursts)
    assert_module1_matches_reference(o)


def test_module1_on_a_long_random_series():
    o = random_observations(np.random.default_rng(5), 20_000, outliers=0.05, bursts=30, gaps=40)
    kept, rep, ref = assert_module1_matches_reference(o)
    assert rep.n_blocks > 10
    assert all(rep.removed[r] > 0 for r in MODULE1_REASONS)


# --------------------------------------------------------------------------------------------
# Module 2
# --------------------------------------------------------------------------------------------


def track(t):
    t = np.asarray(t, dtype=float)
    n = t.size
    return PrismTrack(t, np.zeros((n, 3)), np.broadcast_to(np.eye(3), (n, 3, 3)).copy())


def assert_module2_matches_reference(series, p=P):
    kept, iv, rep = module2(series, p)
    times = [s.t.tolist() for s in series]
    ref_iv, masks, reasons = ref_module2(times, p)
    np.testing.assert_array_equal(iv, ref_iv)
    for s, k, m, r, mask, why in zip(series, kept, masks, reasons, rep.kept_masks, rep.reasons,
                                     strict=True):
        np.testing.assert_array_equal(k.t, s.t[m])
        assert type(k) is type(s)
        np.testing.assert_array_equal(mask, m)
        assert why.tolist() == list(r)
    per = tuple(counts(r, MODULE2_REASONS) for r in reasons)
    assert tuple(dict(c) for c in rep.per_series) == per
    assert dict(rep.removed) == {r: sum(c[r] for c in per) for r in MODULE2_REASONS}
    assert rep.n_in == sum(len(s) for s in series)
    assert rep.n_kept == sum(int(m.sum()) for m in masks)
    assert rep.n_blocks == iv.shape[0]
    assert_masks_reproduce_counts(rep, series, kept, MODULE2_REASONS)
    return kept, iv, rep


def test_intervals_common_to_all_prisms():
    p1 = np.concatenate([np.arange(0.0, 10.01, 0.5), np.arange(20.0, 30.01, 0.5)])
    p2 = np.arange(1.0, 25.01, 0.5)
    p3 = np.concatenate([np.arange(0.2, 7.9, 0.4), np.arange(12.0, 29.01, 0.5)])
    series = [track(p1), track(p2), track(p3)]
    kept, iv, rep = assert_module2_matches_reference(series)
    np.testing.assert_allclose(iv, [[1.0, p3[p3 < 8][-1]], [20.0, 25.0]])
    assert rep.module == "module2" and rep.n_blocks == 2
    # all three prisms are tracked on both intervals: a query grid on them is supported
    for k in kept:
        for a, b in iv:
            inside = k.t[(k.t >= a) & (k.t <= b)]
            assert inside.size and k.t[k.t <= a].size and k.t[k.t >= b].size
            span = k.t[(k.t >= k.t[k.t <= a][-1]) & (k.t <= k.t[k.t >= b][0])]
            assert np.all(np.diff(span) <= P.tau_s)


def test_minimum_duration_tau_l():
    base = np.arange(0.0, 10.01, 0.5)
    # prism 2 is tracked on [0, 1.5] (1.5 s, dropped), then on [5, 7] (exactly tau_l: kept)
    p2 = np.concatenate([[0.0, 0.5, 1.0, 1.5], [5.0, 5.5, 6.0, 6.5, 7.0]])
    kept, iv, rep = assert_module2_matches_reference([track(base), track(p2)])
    np.testing.assert_array_equal(iv, [[5.0, 7.0]])
    assert rep.per_series[1] == {"not_all_tracked": 0, "short_interval": 4}
    assert rep.per_series[0]["short_interval"] == 4  # 0, 0.5, 1.0, 1.5 of prism 1
    np.testing.assert_array_equal(kept[0].t, [5.0, 5.5, 6.0, 6.5, 7.0])
    kept, iv, rep = module2([track(base), track(p2)], FilterParams(tau_l=2.5))
    assert iv.shape == (0, 2) and rep.n_kept == 0


def test_bracketing_measurements_are_kept():
    """The interval starts and ends at other prisms' times; each prism keeps the measurement
    just before its start and just after its end (module docstring, rule 4)."""
    p1 = np.array([0.0, 0.9, 2.0, 3.1, 4.2, 5.3, 6.4])
    p2 = np.array([1.0, 1.8, 2.6, 3.4, 4.2, 5.0])
    kept, iv, rep = assert_module2_matches_reference([track(p1), track(p2)])
    np.testing.assert_array_equal(iv, [[1.0, 5.0]])
    np.testing.assert_array_equal(kept[0].t, [0.9, 2.0, 3.1, 4.2, 5.3])
    np.testing.assert_array_equal(kept[1].t, p2)
    assert rep.per_series[0] == {"not_all_tracked": 2, "short_interval": 0}


def test_isolated_measurements_empty_series_and_one_series():
    # an isolated measurement (its own segment, of zero length) is no interval
    p1 = np.array([0.0, 10.0, 10.5, 11.0, 13.0])
    p2 = np.arange(0.0, 20.0, 0.5)
    kept, iv, rep = assert_module2_matches_reference([track(p1), track(p2)])
    np.testing.assert_array_equal(iv, [[10.0, 13.0]])
    assert 0.0 not in kept[0].t
    kept, iv, rep = assert_module2_matches_reference([track(p2), track([])])
    assert iv.shape == (0, 2) and rep.removed["not_all_tracked"] == p2.size
    kept, iv, rep = assert_module2_matches_reference([track(p1)])
    np.testing.assert_array_equal(iv, [[10.0, 13.0]])


def test_module2_keeps_observations_and_order():
    o1 = obs(np.arange(0.0, 5.0, 0.4), prism="1")
    o2 = obs(np.arange(1.0, 6.0, 0.4), prism="2")
    kept, iv, rep = assert_module2_matches_reference([o1, o2])
    assert [k.prism for k in kept] == ["1", "2"]
    assert all(isinstance(k, Observations) for k in kept)
    assert isinstance(rep, FilterReport)


def test_module2_errors():
    with pytest.raises(InputError, match="at least one time series"):
        module2([])
    with pytest.raises(InputError, match="strictly increasing times in series 1"):
        module2([track([0.0, 1.0]), obs([0.0, 1.0, 1.0])])
    with pytest.raises(InputError, match="finite times in series 0"):
        module2([obs([0.0, np.nan])])


@settings(max_examples=60, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), k=st.integers(1, 4), n=st.integers(0, 120),
       gap_prob=st.sampled_from([0.0, 0.05, 0.2]))
def test_module2_matches_the_brute_force_reference(seed, k, n, gap_prob):
    rng = np.random.default_rng(seed)
    series = []
    for _ in range(k):
        m = int(rng.integers(max(n // 2, 0), n + 1))
        dt = rng.uniform(0.2, 1.0, m) + np.where(rng.random(m) < gap_prob,
                                                 rng.uniform(1.0, 8.0, m), 0.0)
        t = rng.uniform(0, 5) + np.cumsum(dt)
        if rng.random() < 0.5:  # on a 0.1 s grid: equal times across prisms happen
            t = np.unique(np.round(t, 1))
        series.append(track(t))
    assert_module2_matches_reference(series, FilterParams(tau_l=float(rng.choice([0.0, 2.0]))))
