"""``rtsgt batch`` benchmark: N simulated deployments, serially against a local Dask cluster.

Run: ``python benchmarks/bench_batch.py [--deployments 20] [--duration 600] [--workers 2]
[--engine mc]``.

Simulates ``--deployments`` deployments of ``--duration`` s each (``rtsgt simulate``, seeds
1..N), then runs ``rtsgt batch`` on them twice as a user does (the installed console script,
a subprocess): ``--serial``, then ``--workers W`` (a local Dask cluster of W processes), each
into a fresh output folder, and reports for each:

- the wall time of the command;
- the peak memory: the largest sum of the resident set sizes of the command and every process
  it started (the Dask scheduler and workers), sampled every 0.2 s with ``psutil`` (a Dask
  dependency), and the largest single process among them.

Then checks that the two give the same ground truth files. Needs ``dask[distributed]``.
"""

from __future__ import annotations

import argparse
import shutil
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import psutil


def _measure(cmd: list[str]) -> tuple[float, float, float]:
    """Wall time (s), peak total RSS and peak single-process RSS (bytes) of ``cmd`` and its
    descendants."""
    t0 = time.perf_counter()
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    peak = {"total": 0, "single": 0}
    done = threading.Event()

    def sample() -> None:
        root = psutil.Process(proc.pid)
        while not done.is_set():
            try:
                procs = [root, *root.children(recursive=True)]
                rss = []
                for p in procs:
                    try:
                        rss.append(p.memory_info().rss)
                    except psutil.Error:
                        pass
                peak["total"] = max(peak["total"], sum(rss))
                peak["single"] = max(peak["single"], max(rss, default=0))
            except psutil.Error:
                pass
            done.wait(0.2)

    thread = threading.Thread(target=sample, daemon=True)
    thread.start()
    _, err = proc.communicate()
    done.set()
    thread.join()
    wall = time.perf_counter() - t0
    if proc.returncode != 0:
        raise SystemExit(f"{' '.join(cmd)} failed ({proc.returncode}):\n{err}")
    return wall, peak["total"], peak["single"]


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--deployments", type=int, default=20)
    ap.add_argument("--duration", type=float, default=600.0, help="simulated time, s")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--engine", default="mc")
    args = ap.parse_args(argv)
    exe = shutil.which("rtsgt")
    cmd = [exe] if exe else [sys.executable, "-c", "from rtsgt.cli.main import main; main()"]
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        deps = root / "deployments"
        deps.mkdir()
        t0 = time.perf_counter()
        for k in range(1, args.deployments + 1):
            subprocess.run(cmd + ["simulate", str(deps / f"dep{k:02d}"), "--seed", str(k),
                                  "--duration", str(args.duration)],
                           check=True, capture_output=True)
        print(f"{args.deployments} simulated deployments of {args.duration / 60:g} min "
              f"written in {time.perf_counter() - t0:.0f} s; engine {args.engine}")
        results = {}
        for mode, extra in (("serial", ["--serial"]),
                            (f"{args.workers} workers", ["--workers", str(args.workers)])):
            out = root / mode.replace(" ", "-")
            wall, total, single = _measure(cmd + ["batch", str(deps), "-o", str(out),
                                                  "--engine", args.engine, "-q", *extra])
            results[mode] = out
            print(f"  {mode:>10}: {wall:7.1f} s wall, {wall / args.deployments:5.1f} s per "
                  f"deployment; peak memory {total / 2**30:.2f} GiB in all, "
                  f"{single / 2**30:.2f} GiB in one process")
        a, b = results.values()
        same = all((a / d.name / f).read_bytes() == (b / d.name / f).read_bytes()
                   for d in deps.iterdir()
                   for f in ("groundtruth.tum", "groundtruth_covariance.csv"))
        print(f"  same ground truth serially and on Dask: {same}")


if __name__ == "__main__":
    main()
