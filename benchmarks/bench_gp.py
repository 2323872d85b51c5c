"""Benchmark: exact WNOA GP fit + 2 queries per measurement with covariance, N = 1e3 ... 1e6.

For each N, a simulated prism track (a measurement every ~0.4 s, full 3x3 mm-level
covariances) is fitted with a given Qc (block cyclic reduction: means, marginal and lag-one
covariances at every knot) and queried at 2 N random times (position and 3x3 covariance).
The script prints the median wall time of the fit, of the queries, of both, and the time per
measurement, whose flatness across N shows the linear cost; it also times one evaluation of
the marginal likelihood (the unit of work of the Qc estimation) and, for N <= 1e5, a full
isotropic Qc estimation.

Run: ``python benchmarks/bench_gp.py [--sizes 1000 10000 100000 1000000] [--repeat 3]``.
"""

from __future__ import annotations

import argparse
import sys
import time

import numpy as np

from rtsgt.interpolation import fit_qc, fit_track, log_marginal_likelihood


def simulate(n: int, rng: np.random.Generator):
    t = 1.668e9 + np.cumsum(rng.uniform(0.35, 0.45, n))
    xyz = np.cumsum(rng.normal(size=(n, 3)) * 0.05, axis=0)
    a = rng.normal(size=(n, 3, 3)) * 1.5e-3
    cov = a @ np.swapaxes(a, 1, 2) + 1e-6 * np.eye(3)
    return t, xyz, cov


def median_time(fn, repeat: int):
    times, out = [], None
    for _ in range(repeat):
        t0 = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t0)
    return float(np.median(times)), out


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", type=int, nargs="+", default=[1000, 10000, 100000, 1000000])
    parser.add_argument("--repeat", type=int, default=3)
    args = parser.parse_args(argv)
    rng = np.random.default_rng(0)
    sizes, totals = [], []
    print(f"{'N':>8} {'fit (s)':>9} {'2N queries (s)':>15} {'total (s)':>10} "
          f"{'us/meas':>8} {'loglik (s)':>10} {'fit Qc (s)':>10}")
    for n in args.sizes:
        t, xyz, cov = simulate(n, rng)
        tq = rng.uniform(t[0], t[-1], 2 * n)
        track = (t, xyz, cov)
        t_fit, gp = median_time(lambda track=track: fit_track(track, qc=0.05, max_gap_s=10.0),
                                args.repeat)
        t_q, _ = median_time(lambda gp=gp, tq=tq: gp.query(tq), args.repeat)
        t_ll, _ = median_time(lambda track=track: log_marginal_likelihood(track, 0.05),
                              args.repeat)
        if n <= 100_000:
            t_qc, _ = median_time(lambda track=track: fit_qc(track), 1)
            qc_txt = f"{t_qc:>10.2f}"
        else:
            qc_txt = f"{'-':>10}"
        total = t_fit + t_q
        sizes.append(n)
        totals.append(total)
        print(f"{n:>8} {t_fit:>9.3f} {t_q:>15.3f} {total:>10.3f} {total / n * 1e6:>8.2f} "
              f"{t_ll:>10.3f} {qc_txt}", flush=True)
    if len(sizes) > 1:
        slope = np.polyfit(np.log(sizes), np.log(totals), 1)[0]
        print(f"fit + queries: time ~ N^{slope:.2f} over N = {sizes[0]} ... {sizes[-1]} "
              "(1 = linear)")
    if 100_000 in sizes:
        t5 = totals[sizes.index(100_000)]
        print(f"N = 100000: {t5:.2f} s (target: under 5 s) -> {'ok' if t5 < 5 else 'SLOW'}")
    print("(wall times on this machine; indicative when it is shared)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
