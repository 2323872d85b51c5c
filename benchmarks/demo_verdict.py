"""The verdict ``rtsgt demo`` ends with, over many seeds: the split test against the fallback.

Run: ``python benchmarks/demo_verdict.py [--seeds 0-10] [--duration 600] [--engine mc]
[--samples 1000]``

For each seed, what ``rtsgt demo --seed S`` does without its report: simulate a deployment
(:mod:`rtsgt.simulation`, ``numpy.random.default_rng(S)``), write and read back its files, run
the pipeline with ``seed = S`` and compare the ground truth with the truth
(:func:`rtsgt.simulation.compare.compare_to_truth`), once with the run's shared factor (the
split test, the demo's verdict) and once without (the autocorrelation test of the NEES series
the demo used before). Prints one JSON line per seed and the counts of consistent verdicts
(docs/self-checks.md#the-runs-verdict quotes them).
"""

from __future__ import annotations

import argparse
import json
import tempfile
import warnings
from pathlib import Path

import numpy as np

from rtsgt.io.deployment import load_deployment
from rtsgt.pipeline import run_pipeline
from rtsgt.simulation import SimulationConfig, simulate_deployment, write_deployment
from rtsgt.simulation.compare import compare_to_truth


def seeds(text: str) -> list[int]:
    lo, _, hi = text.partition("-")
    return list(range(int(lo), int(hi or lo) + 1))


def one(seed: int, args, tmp: Path) -> dict:
    sim = simulate_deployment(SimulationConfig(duration_s=args.duration),
                              np.random.default_rng(seed))
    data, options = load_deployment(write_deployment(sim, tmp / f"dep-{seed}"))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        rec = run_pipeline(data, options.updated(seed=seed, engine=args.engine,
                                                 samples=args.samples))
    gt = rec.groundtruth
    p, q = sim.truth_at(gt.t)
    fallback = compare_to_truth(gt, p, q)
    split = compare_to_truth(gt, p, q, split=rec.groundtruth_split)
    out = {"seed": seed}
    for name, n_fb, n_sp in (("position", fallback.nees_position, split.nees_position),
                             ("pose", fallback.nees_pose, split.nees_pose)):
        out[name] = {"split": n_sp.consistent, "autocorrelation": n_fb.consistent,
                     "nees_per_dof": n_sp.mean / n_sp.dof,
                     "shared_chi2": n_sp.split.shared.statistic,
                     "shared_dof": n_sp.split.shared.dof,
                     "varying_per_dof": n_sp.split.varying.mean / n_sp.dof,
                     "varying_upper": n_sp.split.varying.mean_interval[1] / n_sp.dof}
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", default="0-10", help="first-last (inclusive)")
    ap.add_argument("--duration", type=float, default=600.0)
    ap.add_argument("--engine", default="mc")
    ap.add_argument("--samples", type=int, default=1000)
    args = ap.parse_args()
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for seed in seeds(args.seeds):
            rows.append(one(seed, args, Path(tmp)))
            print(json.dumps(rows[-1]), flush=True)
    for name in ("pose", "position"):
        for test in ("split", "autocorrelation"):
            n = sum(r[name][test] for r in rows)
            print(f"{name}: {test} test consistent in {n} of {len(rows)}")


if __name__ == "__main__":
    main()
