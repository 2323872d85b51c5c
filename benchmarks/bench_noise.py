"""Throughput of the per-measurement noise engines (plain script; prints medians).

Run: ``python benchmarks/bench_noise.py [--quick]``

- Monte Carlo: measurement-samples per second for the sources instrument + tilt + atmosphere
  (1e4 measurements x 1000 samples by default), full ``propagate`` call: the total covariance
  and the covariance of each source alone (common random numbers), with 1 and 2 threads, and
  the total alone is not offered separately (every call returns all per-source covariances).
- Linear: measurements per second for the same sources (and all five, with calibration).

Targets (issue 2): >= 2e7 measurement-samples/s (MC), >= 1e6 measurements/s (linear).
"""

from __future__ import annotations

import argparse
import os
import platform
import statistics
import time

import numpy as np

from rtsgt.geometry.so3 import exp_so3
from rtsgt.geometry.transform import RigidTransform
from rtsgt.measurement.instruments import TRIMBLE_S7
from rtsgt.noise import NoiseModel, propagate
from rtsgt.types import Observations, WeatherSeries


def make_inputs(n: int, seed: int = 0):
    rng = np.random.default_rng(seed)
    t = np.cumsum(rng.uniform(0.2, 0.5, n))
    obs = Observations(
        t=t,
        hz=rng.uniform(0, 2 * np.pi, n),
        v=rng.uniform(np.radians(60), np.radians(120), n),
        d=rng.uniform(2.0, 300.0, n),
        additive_constant=0.01,
    )
    weather = WeatherSeries(
        t=np.array([t[0] - 1, t[-1] + 1]),
        temperature_c=np.array([5.0, 7.0]),
        pressure_hpa=np.array([935.0, 937.0]),
        humidity_pct=np.array([70.0, 80.0]),
    )
    T = RigidTransform(
        exp_so3([0.0, 0.0, 2.8]), np.array([-0.66, -1.30, 0.29]),
        np.diag([1e-6, 1e-6, 2e-6, 1e-9, 1e-9, 4e-8]), "world", "station_2",
    )
    return obs, weather, T


def timeit(fn, repeats: int) -> list[float]:
    out = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        out.append(time.perf_counter() - t0)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="smaller sizes (smoke run)")
    ap.add_argument("--repeats", type=int, default=5)
    args = ap.parse_args()

    n_mc, m_mc, n_lin = (10_000, 1000, 1_000_000)
    if args.quick:
        n_mc, m_mc, n_lin = (1000, 1000, 100_000)
    print(f"python {platform.python_version()}, numpy {np.__version__}, "
          f"{os.cpu_count()} CPU(s), {platform.processor() or platform.machine()}")

    model3 = NoiseModel(TRIMBLE_S7, sources=("instrument", "tilt", "atmosphere"))
    obs, weather, T = make_inputs(n_mc)
    for workers in (1, 2):
        rng = np.random.default_rng(1)
        times = timeit(
            lambda w=workers, r=rng: propagate(
                obs, model3, weather=weather, T_world_station=T, engine="mc", samples=m_mc,
                rng=r, workers=w,
            ),
            args.repeats,
        )
        med = statistics.median(times)
        print(f"MC  instrument+tilt+atmosphere, {n_mc} x {m_mc} samples, workers={workers}: "
              f"median {med:.3f} s -> {n_mc * m_mc / med:.3g} measurement-samples/s "
              f"(target 2e7)")

    obs_l, weather_l, T_l = make_inputs(n_lin)
    for label, model in (
        ("instrument+tilt+atmosphere", model3),
        ("all five sources", NoiseModel(TRIMBLE_S7)),
    ):
        times = timeit(
            lambda m=model: propagate(obs_l, m, weather=weather_l, T_world_station=T_l),
            args.repeats,
        )
        med = statistics.median(times)
        print(f"linear {label}, {n_lin} measurements: median {med:.3f} s -> "
              f"{n_lin / med:.3g} measurements/s (target 1e6)")


if __name__ == "__main__":
    main()
