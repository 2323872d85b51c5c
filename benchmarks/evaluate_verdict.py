"""The NEES verdict of ``rtsgt evaluate`` on the simulated truth and on a biased truth.

Run: ``python benchmarks/evaluate_verdict.py [--deployments 100] [--duration 120]
[--engine linear] [--samples 300] [--bias-m 0.01] [--align none] [--first-seed 7000]``

For each deployment ``first_seed + k`` (:mod:`rtsgt.simulation`): simulate, write the files,
read them back, run the pipeline, write the run directory and load its continuous ground
truth (:func:`rtsgt.app.read_ground_truth`), as ``rtsgt evaluate``
does. The exact truth (``sim.truth_at``) at the run's pose times is then evaluated as an
estimate (no covariance) through :func:`rtsgt.evaluation.evaluate`, once as it is and once
shifted by a constant bias of ``--bias-m`` along a random horizontal direction. Counted: the
share of deployments whose pose NEES verdict (``nees.pose.consistent``) says "consistent"
for the truth and "inconsistent" for the biased truth, with the split test (the run's shared
factor) and, for comparison, with the autocorrelation verdict the evaluation falls back to
without it.
"""

from __future__ import annotations

import argparse
import tempfile
import time
import warnings
from pathlib import Path

import numpy as np

from rtsgt.app import read_ground_truth
from rtsgt.evaluation import evaluate
from rtsgt.io.deployment import load_deployment
from rtsgt.io.run_dir import write_run
from rtsgt.pipeline import run_pipeline
from rtsgt.simulation import SimulationConfig, simulate_deployment, write_deployment
from rtsgt.types import PoseTrajectory


def one(seed: int, args, tmp: Path) -> dict:
    sim = simulate_deployment(SimulationConfig(duration_s=args.duration),
                              np.random.default_rng(seed))
    data, opts = load_deployment(write_deployment(sim, tmp / f"dep-{seed}"))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        rec = run_pipeline(data, opts.updated(seed=seed, engine=args.engine,
                                              samples=args.samples))
        run = write_run(rec, tmp / f"run-{seed}")
        gt = read_ground_truth(run)
        t = rec.groundtruth.t
        p, q = sim.truth_at(t)
        ang = np.random.default_rng(seed + 1).uniform(0, 2 * np.pi)
        bias = args.bias_m * np.array([np.cos(ang), np.sin(ang), 0.0])
        out = {}
        for name, pos in (("truth", p), ("biased", p + bias)):
            res = evaluate(gt, PoseTrajectory(t, pos, q), align=args.align)
            nees = res.nees.pose
            out[name] = {"split": nees.consistent, "autocorrelation": nees.mean_ok
                         and nees.fraction_ok, "mean": nees.mean / 6,
                         "shared": nees.split.shared.statistic / max(nees.split.shared.dof, 1),
                         "varying": nees.split.varying.mean / 6,
                         "shared_ok": nees.split.shared.consistent,
                         "varying_ok": nees.split.varying.consistent}
    return out


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--deployments", type=int, default=100)
    ap.add_argument("--duration", type=float, default=120.0)
    ap.add_argument("--engine", default="linear")
    ap.add_argument("--samples", type=int, default=300)
    ap.add_argument("--bias-m", type=float, default=0.01)
    ap.add_argument("--align", default="none")
    ap.add_argument("--first-seed", type=int, default=7000)
    ap.add_argument("--verbose", action="store_true")
    args = ap.parse_args(argv)
    t0 = time.perf_counter()
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for k in range(args.deployments):
            r = one(args.first_seed + k, args, Path(tmp))
            rows.append(r)
            if args.verbose:
                tr, bi = r["truth"], r["biased"]
                print(f"{args.first_seed + k}: truth {tr['split']!s:5} shared/dof "
                      f"{tr['shared']:.2f} varying/dof {tr['varying']:.2f} NEES/dof "
                      f"{tr['mean']:.2f} | biased {bi['split']!s:5} shared/dof {bi['shared']:.1f}",
                      flush=True)
    n = len(rows)
    ok = np.mean([r["truth"]["split"] for r in rows])
    caught = np.mean([not r["biased"]["split"] for r in rows])
    ok_ac = np.mean([r["truth"]["autocorrelation"] for r in rows])
    caught_ac = np.mean([not r["biased"]["autocorrelation"] for r in rows])
    print(f"{n} deployments x {args.duration:g} s, engine {args.engine}, align {args.align}, "
          f"bias {1e3 * args.bias_m:g} mm ({time.perf_counter() - t0:.0f} s)")
    print(f"split test:            truth consistent {ok:.2f}, biased inconsistent {caught:.2f}")
    print(f"  truth: shared part consistent {np.mean([r['truth']['shared_ok'] for r in rows]):.2f},"
          f" varying part consistent {np.mean([r['truth']['varying_ok'] for r in rows]):.2f}")
    print(f"autocorrelation test:  truth consistent {ok_ac:.2f}, biased inconsistent "
          f"{caught_ac:.2f}")


if __name__ == "__main__":
    main()
