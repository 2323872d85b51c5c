"""Honesty of the ground truth's covariance, per pose engine, pooled over simulated deployments.

Run: ``python benchmarks/honesty.py [--deployments 120] [--duration 150] [--engines mc ut linear]
[--samples 300] [--first-seed 5000] [--sources all] [--registration weighted|unweighted]
[--prior wnoa|wnoj|select]``

For each engine, every deployment ``first_seed + k`` is simulated (:mod:`rtsgt.simulation`),
written as files, read back and run through the whole pipeline; its ground truth is compared
with the exact truth at the same times. The position NEES (3 dof) and the pose NEES (6 dof) are
pooled over all poses of all deployments: ``mean / dof`` should be 1 and the share inside the
95 % region 0.95. Every systematic error (GCP calibration, clock offsets, reference survey,
weather) is drawn once per deployment, so the spread of the pooled figures is set by the
number of deployments, not of poses: about +-0.04 on ``mean / dof`` for 120 deployments.

``--registration`` picks the fit of the prisms onto their surveyed positions
(:mod:`rtsgt.pose.weighted` or the paper's unweighted one; default: the ``[pose]`` default,
:data:`rtsgt.pose.estimate.DEFAULT_REGISTRATION`). ``--sources`` turns the simulated noise sources off one by one (``instrument`` keeps only the
instrument's noise; ``no-<source>`` drops one), to see which one drives a discrepancy.
``--prior`` sets the GP's motion prior (``[interpolation] prior``; default: the option's
default). Also printed per engine: how many tracks got each prior, and per regime of the block
cross-validation self-check the pooled NEES / dof and the share of deployments it flags
optimistic and pessimistic (the simulation has none of the reality effects, so every flag is a
false alarm or a model error).
"""

from __future__ import annotations

import argparse
import tempfile
import time
import warnings
from pathlib import Path

import numpy as np
from scipy.stats import chi2

from rtsgt.io.deployment import load_deployment
from rtsgt.pipeline import run_pipeline
from rtsgt.pose.estimate import DEFAULT_REGISTRATION, REGISTRATIONS
from rtsgt.simulation import SimulationConfig, simulate_deployment, write_deployment
from rtsgt.simulation.compare import compare_to_truth

FLAGS = {"instrument": "noise_instrument", "tilt": "noise_tilt", "weather": "noise_weather",
         "time_sync": "noise_time_sync", "survey": "noise_survey"}


def _flags(sources: str) -> dict:
    if sources == "all":
        return {}
    if sources == "instrument":
        return {v: k == "instrument" for k, v in FLAGS.items()}
    if sources.startswith("no-") and sources[3:] in FLAGS:
        return {FLAGS[sources[3:]]: False}
    raise SystemExit(f"unknown --sources {sources!r}")


def pooled(engine: str, seeds, duration: float, samples: int, flags: dict, tmp: Path,
           registration: str = DEFAULT_REGISTRATION, prior: str | None = None) -> dict:
    n3, n6, err = [], [], []
    priors: dict[str, int] = {}
    cv_flags: dict[str, int] = {}
    extra = {} if prior is None else {"prior": prior}
    for seed in seeds:
        sim = simulate_deployment(SimulationConfig(duration_s=duration, **flags),
                                  np.random.default_rng(seed))
        data, opts = load_deployment(write_deployment(sim, tmp / f"{engine}-{seed}"))
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            result = run_pipeline(data, opts.updated(seed=seed, engine=engine, samples=samples,
                                                     registration=registration, **extra))
        p, q = sim.truth_at(result.groundtruth.t)
        c = compare_to_truth(result.groundtruth, p, q)
        n3.append(c.nees_position.values)
        n6.append(c.nees_pose.values)
        err.append(c.position_error_m)
        for g in result.prior.values():
            priors[g] = priors.get(g, 0) + 1
        cv = result.self_checks["block_cv"]
        for name, v in [("overall", cv["overall"]), *cv["regimes"].items()]:
            f = cv_flags.setdefault(name, {"optimistic": 0, "pessimistic": 0, "nees": 0.0,
                                           "dof": 0})
            if v.get("verdict") in ("optimistic", "pessimistic"):
                f[v["verdict"]] += 1
            if v.get("nees_per_dof") is not None:
                f["nees"] += v["nees_per_dof"] * 3 * v["measurements"]
                f["dof"] += 3 * v["measurements"]
    a3, a6 = np.concatenate(n3), np.concatenate(n6)
    return {"poses": a3.size, "nees3": a3.mean() / 3, "in3": np.mean(a3 <= chi2.ppf(0.95, 3)),
            "nees6": a6.mean() / 6, "in6": np.mean(a6 <= chi2.ppf(0.95, 6)),
            "err_mm": 1e3 * np.median(np.concatenate(err)), "priors": priors,
            "cv": cv_flags, "deployments": len(seeds)}


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--deployments", type=int, default=120)
    ap.add_argument("--duration", type=float, default=150.0)
    ap.add_argument("--engines", nargs="+", default=["mc", "ut", "linear"])
    ap.add_argument("--samples", type=int, default=300)
    ap.add_argument("--first-seed", type=int, default=5000)
    ap.add_argument("--sources", default="all")
    ap.add_argument("--registration", choices=REGISTRATIONS, default=DEFAULT_REGISTRATION)
    ap.add_argument("--prior", default=None, choices=["wnoa", "wnoj", "select"])
    args = ap.parse_args(argv)
    seeds = range(args.first_seed, args.first_seed + args.deployments)
    print(f"{args.deployments} deployments x {args.duration:g} s, sources {args.sources}, "
          f"{args.registration} registration, prior {args.prior or 'default'}")
    print(f"{'engine':<7} {'poses':>7} {'NEES3/3':>8} {'in 95%':>7} {'NEES6/6':>8} "
          f"{'in 95%':>7} {'median err':>11} {'time':>7}")
    with tempfile.TemporaryDirectory() as tmp:
        for engine in args.engines:
            t0 = time.perf_counter()
            r = pooled(engine, seeds, args.duration, args.samples, _flags(args.sources), Path(tmp),
                       args.registration, args.prior)
            print(f"{engine:<7} {r['poses']:>7d} {r['nees3']:>8.3f} {r['in3']:>7.3f} "
                  f"{r['nees6']:>8.3f} {r['in6']:>7.3f} {r['err_mm']:>8.2f} mm "
                  f"{time.perf_counter() - t0:>6.0f}s")
            n = r["deployments"]
            print(f"        priors of the tracks: {r['priors']}; block CV, pooled NEES / dof "
                  "(deployments flagged optimistic / pessimistic): " + ", ".join(
                      f"{k} {v['nees'] / max(v['dof'], 1):.2f} ({v['optimistic'] / n:.0%} / "
                      f"{v['pessimistic'] / n:.0%})" for k, v in r["cv"].items()))


if __name__ == "__main__":
    main()
