"""Time of the noise-source analysis of a 30-minute simulated deployment (plain script).

Run: ``python benchmarks/bench_analysis.py [--duration 1800] [--engine linear] [--repeats 3]``

A deployment is simulated (:func:`rtsgt.simulation.simulate_deployment`), written as the
files of a real one, loaded and run through :func:`rtsgt.pipeline.run_pipeline` with the
linear engine (not timed against the target), then written as a run directory. Timed, median
of ``--repeats``:

- ``analyze``: the per-source analysis of the in-memory run record (prism norms by range bin,
  and the pose engine run again per source at every kept pose);
- ``analyze_dir``: the same from the run directory (reading included);
- the four figures (drawn and saved as PNG and SVG);
- the HTML report (rendering with the 3D view, written to disk).

Target (issue 6): the analysis of a 30-minute deployment under 2 minutes with the linear
engine (``analyze`` + figures + report).
"""

from __future__ import annotations

import argparse
import os
import platform
import statistics
import tempfile
import time
from pathlib import Path

import numpy as np


def timeit(fn, repeats: int):
    times, out = [], None
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t0)
    return times, out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--duration", type=float, default=1800.0, help="simulated seconds")
    ap.add_argument("--engine", default="linear", choices=("linear", "ut", "mc"))
    ap.add_argument("--samples", type=int, default=1000)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--seed", type=int, default=1)
    args = ap.parse_args()

    from rtsgt.io.deployment import load_deployment
    from rtsgt.io.run_dir import read_run, write_run
    from rtsgt.pipeline import run_pipeline
    from rtsgt.report.analysis import analyze, analyze_dir
    from rtsgt.report.figures import draw_all, save_figures
    from rtsgt.report.html import write_report_file
    from rtsgt.simulation import SimulationConfig, simulate_deployment, write_deployment

    print(f"python {platform.python_version()}, numpy {np.__version__}, "
          f"{os.cpu_count()} CPUs, {platform.machine()}")
    with tempfile.TemporaryDirectory(prefix="rtsgt-bench-analysis-") as tmp:
        tmp = Path(tmp)
        t0 = time.perf_counter()
        sim = simulate_deployment(SimulationConfig(duration_s=args.duration),
                                  np.random.default_rng(args.seed))
        config = write_deployment(sim, tmp / "deployment", name="bench-analysis")
        data, options = load_deployment(config)
        options = options.updated(engine=args.engine, samples=args.samples, seed=args.seed)
        result = run_pipeline(data, options)
        run_dir = write_run(result, tmp / "run")
        n_meas = sum(len(tr) for tr in result.computation.tracks.values())
        print(f"deployment: {args.duration:.0f} s simulated, {n_meas} measurements, "
              f"{len(result.computation.estimate)} query times, {len(result.groundtruth)} kept poses "
              f"({args.engine} engine); simulate + pipeline + write: "
              f"{time.perf_counter() - t0:.1f} s (not part of the target)")

        t_run, analysis = timeit(lambda: analyze(result), args.repeats)
        t_dir, _ = timeit(lambda: analyze_dir(run_dir), args.repeats)
        data_dir = read_run(run_dir)
        t_fig, _ = timeit(lambda: save_figures(draw_all(data_dir, analysis), tmp / "figs"),
                          args.repeats)
        t_html, info = timeit(lambda: write_report_file(data_dir, analysis,
                                                         tmp / "report.html"), args.repeats)
        runs = {"analyze": t_run, "analyze_dir": t_dir, "figures": t_fig,
                "report": t_html}
        med = {k: statistics.median(v) for k, v in runs.items()}
        for k, v in runs.items():
            print(f"{k:12s} median {med[k]:7.2f} s  (runs: "
                  f"{', '.join(f'{x:.2f}' for x in v)})")
        total = med["analyze"] + med["figures"] + med["report"]
        print(f"report: {info.size_bytes / 1e6:.1f} MB, {info.n_ellipsoids} ellipsoids")
        print(f"analysis + figures + report: {total:.1f} s (target < 120 s): "
              f"{'OK' if total < 120 else 'MISSED'}")
        print("medians (mm): " + ", ".join(f"{s} {analysis.median_mm[s]:.3g}"
                                           for s in analysis.sources))


if __name__ == "__main__":
    main()
