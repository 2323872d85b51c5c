"""Benchmark: the leave-one-out Qc search of one prism track, its time and its memory.

For each N, a simulated prism track (a measurement every ~0.4 s, full 3x3 mm-level
covariances) is scored under 4 candidate ``Qc`` at once (the unit of work of the per-axis
search: a point and its three forward steps, :meth:`rtsgt.interpolation.loo.LooScorer.scores`),
and, for N <= 1e4, fitted by the whole search (:func:`rtsgt.interpolation.prisms.fit_prism_gp`
with ``"loo"``). The script prints the median wall time and the peak of the memory traced by
``tracemalloc`` during one call, also per knot and candidate in blocks of 6x6 doubles (the
system's unit: 12.8 blocks before issue 25, about 3 since).

Run: ``python benchmarks/bench_loo.py [--sizes 1000 10000 100000] [--repeat 3]``.
"""

from __future__ import annotations

import argparse
import sys
import time
import tracemalloc

import numpy as np

from rtsgt.interpolation.loo import LooScorer
from rtsgt.interpolation.prisms import fit_prism_gp

BLOCK_BYTES = 6 * 6 * 8


def simulate(n: int, rng: np.random.Generator):
    t = 1.668e9 + np.cumsum(rng.uniform(0.35, 0.45, n))
    xyz = np.cumsum(np.cumsum(rng.normal(size=(n, 3)) * 0.01, axis=0), axis=0) * 0.4
    a = rng.normal(size=(n, 3, 3)) * 1.5e-3
    cov = a @ np.swapaxes(a, 1, 2) + 1e-6 * np.eye(3)
    return t, xyz, cov


def measure(fn, repeat: int) -> tuple[float, int]:
    """Median wall time of ``fn()`` over ``repeat`` calls, s, and its traced peak, bytes."""
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    tracemalloc.start()
    try:
        fn()
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    return float(np.median(times)), peak


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", type=int, nargs="+", default=[1000, 10000, 100000])
    parser.add_argument("--repeat", type=int, default=3)
    args = parser.parse_args(argv)
    rng = np.random.default_rng(0)
    qcs = [np.diag([0.02, 0.01, 0.001]) * f for f in (1.0, 1.001, 1.002, 1.003)]
    print(f"{'N':>8} {'4 candidates (s)':>17} {'peak (MiB)':>11} {'blocks/knot/cand':>17} "
          f"{'whole search (s)':>17} {'peak (MiB)':>11}")
    for n in args.sizes:
        track = simulate(n, rng)
        scorer = LooScorer(track, 3.0)
        t_unit, peak_unit = measure(lambda s=scorer: s.scores(qcs), args.repeat)
        line = (f"{n:>8} {t_unit:>17.3f} {peak_unit / 2**20:>11.1f} "
                f"{peak_unit / (len(qcs) * n * BLOCK_BYTES):>17.2f}")
        if n <= 10000:
            t_fit, peak_fit = measure(lambda tr=track: fit_prism_gp(tr, "loo", 3.0, "bench"),
                                      1)
            line += f" {t_fit:>17.2f} {peak_fit / 2**20:>11.1f}"
        print(line, flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
