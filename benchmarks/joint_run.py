"""``rtsgt run`` with the per-prism and the joint engine on the same deployment.

Run: ``python benchmarks/joint_run.py [--duration 3600] [--seed 0] [--engines mc joint
joint-noclocks] [--modelled] [--deployment TOML]``

Simulates the deployment (the simulator's defaults, ``--modelled``: its survey noise and
clock offsets off, what the joint engine models today; or takes a real one's TOML with
``--deployment``, no truth), then runs ``rtsgt run --engine E`` on it, one process
each under ``/usr/bin/time -v`` (wall and CPU time, peak resident memory); ``joint-noclocks`` is the
joint engine with ``[pose] clocks = false``. Against the simulation's truth: the kept poses'
NEES / dof, the share whose 95 % region holds the truth, the median position sigma; from
``summary.json``: the verdict, the joint section's clocks, chi^2 per row and iterations.
docs/pipeline.md#measured-the-joint-engine-in-a-run.
"""

from __future__ import annotations

import argparse
import json
import re
import shutil
import subprocess
import tempfile
from pathlib import Path

import numpy as np

from rtsgt.geometry.so3 import quat_xyzw_to_matrix
from rtsgt.geometry.transform import perturbation
from rtsgt.io.run_dir import read_run
from rtsgt.simulation import SimulationConfig, simulate_deployment, write_deployment

CHI2_95_6 = 12.591587243743977


def run_once(toml: Path, out: Path, engine: str) -> dict:
    """``rtsgt run`` of ``toml`` with ``engine`` (``joint-noclocks``: clocks off) under
    ``/usr/bin/time -v``: wall and CPU s, peak MiB and the verdict line."""
    if engine == "joint-noclocks":
        text = toml.read_text()
        text = (text.replace("[pose]\n", "[pose]\nclocks = false\n", 1) if "[pose]\n" in text
                else text + "\n[pose]\nclocks = false\n")
        toml = toml.with_name("deployment_noclocks.toml")
        toml.write_text(text)
        engine = "joint"
    cmd = ["/usr/bin/time", "-v", "rtsgt", "run", str(toml), "--engine", engine, "--out",
           str(out), "--force", "-q"]
    res = subprocess.run(cmd, capture_output=True, text=True, check=False)
    if res.returncode != 0:
        raise SystemExit(f"{' '.join(cmd)} failed:\n{res.stderr[-2000:]}")
    wall = re.search(r"Elapsed \(wall clock\) time.*: (?:(\d+):)?(\d+):([\d.]+)", res.stderr)
    h, m, s = (float(x) if x else 0.0 for x in wall.groups())
    peak = float(re.search(r"Maximum resident set size \(kbytes\): (\d+)", res.stderr).group(1))
    cpu = sum(float(re.search(rf"{k} time \(seconds\): ([\d.]+)", res.stderr).group(1))
              for k in ("User", "System"))
    return {"wall_s": 3600 * h + 60 * m + s, "cpu_s": cpu, "peak_mib": peak / 1024, "verdict":
            res.stdout.strip().splitlines()[-1][:160]}


def scores(out: Path, sim) -> dict:
    """NEES / dof, 95 % coverage and median position sigma of the run at ``out`` against the
    simulation's truth (None without one), and the joint section's numbers."""
    rec = read_run(out)
    gt = rec.groundtruth
    sig = np.median(np.sqrt(np.einsum("kii->k", gt.cov[:, :3, :3]))) * 1e3
    row = {"kept": len(gt), "queried": int(rec.prisms_t.size), "sigma_mm": float(sig)}
    if sim is not None:
        p, q = sim.truth_at(gt.t)
        e = perturbation(quat_xyzw_to_matrix(q), p, quat_xyzw_to_matrix(gt.quat_xyzw),
                         gt.position)
        n = np.einsum("ki,kij,kj->k", e, np.linalg.inv(gt.cov), e)
        row |= {"nees_dof": float(n.mean() / 6), "cover95": float(np.mean(n < CHI2_95_6))}
    j = rec.joint
    if j:
        row |= {"chi2": j["chi2_per_dof"], "iterations": j["iterations"],
                "converged": j["converged"], "clocks_ms": {
                    s: (round(c["start_ms"], 2), round(c["end_ms"], 2),
                        round(c["median_sigma_ms"], 3)) for s, c in j["clocks"].items()},
                "station_shift_sigmas": {s: None if v["shift_sigmas"] is None else
                                         round(float(np.max(np.abs(v["shift_sigmas"]))), 2)
                                         for s, v in j["stations"].items()}}
    row["timings_s"] = {k: round(v, 1) for k, v in rec.summary["timings_s"].items()
                        if v > 0.5}
    return row


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--duration", type=float, default=3600.0)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--engines", nargs="+", default=["mc", "joint", "joint-noclocks"])
    ap.add_argument("--deployment", type=Path, default=None)
    ap.add_argument("--modelled", action="store_true",
                    help="survey noise and clock offsets off (what the joint engine models)")
    ap.add_argument("--work", type=Path, default=None)
    a = ap.parse_args()
    work = a.work or Path(tempfile.mkdtemp(prefix="joint_run_"))
    sim = None
    if a.deployment is not None:  # a copy: the clocks-off TOML is written beside it
        toml = Path(shutil.copytree(a.deployment.parent, work / "deployment",
                                    dirs_exist_ok=True)) / a.deployment.name
    else:
        off = {"noise_survey": False, "noise_time_sync": False} if a.modelled else {}
        sim = simulate_deployment(SimulationConfig(duration_s=a.duration, **off),
                                  np.random.default_rng(a.seed))
        toml = write_deployment(sim, work / "deployment", overwrite=True)
    for engine in a.engines:
        out = work / f"run_{engine}"
        row = run_once(Path(toml), out, engine) | scores(out, sim)
        print(engine, json.dumps(row), flush=True)


if __name__ == "__main__":
    main()
