"""Many deployments at once (``rtsgt batch``): one task per deployment, serially or on Dask.

Orchestration only: each task is ``rtsgt run``'s single-deployment run
(:func:`rtsgt.app.run_deployment`), the summary is read back from each run's
``summary.json`` (:mod:`rtsgt.io.batch_summary`). :func:`find_deployments` finds the
deployments, :func:`deployment_seed` gives each a seed from its name and the base seed alone,
a complete run with the same inputs is skipped, a failure is one line (:func:`run_task`
never raises), and Dask is imported only when used (:func:`dask_client`). Deployments, seeds,
resuming, failures and Dask: docs/batch.md.
"""

from __future__ import annotations

import hashlib
import json
import os
import secrets
import time
import warnings
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

from rtsgt.app.run import run_deployment
from rtsgt.errors import InputError, RtsgtError
from rtsgt.io.config import load_config
from rtsgt.io.deployment import DEPLOYMENT_TOML
from rtsgt.io.output_dir import MANIFEST, complete_output, output_kind
from rtsgt.io.run_dir import read_summary
from rtsgt.parallel import available_cores

#: What each deployment's task ends with.
STATUSES = ("done", "skipped", "failed")
#: Memory a worker of the default local cluster is given, bytes (a ten-minute deployment
#: with the Monte Carlo engine peaks well under it: docs/benchmarks.md#speed).
MEMORY_PER_WORKER = 2 * 1024**3
#: Dask's configuration of the environment its nanny gives each worker process.
NANNY_ENVIRON = "distributed.nanny.pre-spawn-environ"


@dataclass(frozen=True)
class Deployment:
    """A deployment of a batch: its name (unique in the batch) and configuration file."""

    name: str
    config: Path


@dataclass(frozen=True)
class BatchTask:
    """One deployment's run, picklable (sent to a worker): its ``name``, TOML ``config``, run
    directory ``out`` (``OUT/<name>``), ``seed`` (:func:`deployment_seed`), the command line's
    ``options``, the ``inputs`` ``summary.json`` records (compared on resume), ``force`` (replace
    an rtsgt output) and ``report`` (add the HTML report)."""

    name: str
    config: Path
    out: Path
    seed: int
    options: dict = field(default_factory=dict)
    inputs: dict = field(default_factory=dict)
    force: bool = False
    report: bool = False


@dataclass(frozen=True)
class Outcome:
    """How one deployment's task ended: ``status`` among :data:`STATUSES`, the one-line
    ``message`` of a failure, the seconds the run took (0 when skipped)."""

    name: str
    status: str
    seed: int
    out: Path
    config: Path
    message: str = ""
    elapsed_s: float = 0.0


def deployment_seed(base_seed: int, name: str) -> int:
    """The seed of deployment ``name`` in a batch of base seed ``base_seed`` (module
    docstring): stable across runs, machines and Python versions."""
    if isinstance(base_seed, bool) or int(base_seed) != base_seed or base_seed < 0:
        raise InputError(f"Expected a base seed >= 0 (an integer), got {base_seed!r}")
    digest = hashlib.sha256(f"rtsgt-batch\0{int(base_seed)}\0{name}".encode()).digest()
    return int.from_bytes(digest[:8], "big") >> 1


def _skipped_folder(path: Path) -> bool:
    kind = output_kind(path) if (path / MANIFEST).is_file() else None
    return kind is not None and kind != "deployment"


def find_deployments(paths: Iterable[str | os.PathLike], *, out: str | os.PathLike | None = None
                     ) -> tuple[list[Deployment], list[str]]:
    """The deployments under ``paths`` (docs/batch.md#deployments), sorted by name, and the
    notes of what was skipped.

    Raises
    ------
    InputError
        A path that does not exist, a file that is not a TOML, two deployments of the same
        name, or no deployment at all.
    """
    out_dir = Path(os.path.abspath(out)) if out is not None else None
    found: list[Deployment] = []
    notes: list[str] = []
    for given in paths:
        p = Path(os.path.abspath(given))
        if not p.exists():
            raise InputError("no such file or folder", given)
        if p.is_file():
            if p.suffix.lower() != ".toml":
                raise InputError("expected a deployment TOML, a deployment folder or a folder "
                                 "of them", given)
            found.append(Deployment(p.stem, p))
            continue
        if (p / DEPLOYMENT_TOML).is_file():
            found.append(Deployment(p.name, p / DEPLOYMENT_TOML))
            continue
        for entry in sorted(p.iterdir()):
            if entry.name.startswith(".") or entry == out_dir:
                continue
            if entry.is_file() and entry.suffix.lower() == ".toml":
                found.append(Deployment(entry.stem, entry))
            elif entry.is_dir() and not _skipped_folder(entry):
                if (entry / DEPLOYMENT_TOML).is_file():
                    found.append(Deployment(entry.name, entry / DEPLOYMENT_TOML))
                else:
                    notes.append(f"skipped {entry}: no {DEPLOYMENT_TOML} (rtsgt init writes "
                                 "one for an RTS_project folder)")
    by_name: dict[str, list[Deployment]] = {}
    for d in found:
        by_name.setdefault(d.name, []).append(d)
    for name, same in by_name.items():
        if len(same) > 1:
            raise InputError(f"{len(same)} deployments named {name!r} ("
                             + ", ".join(str(d.config) for d in same)
                             + "): their run directories would be the same; rename one")
    if not found:
        raise InputError("no deployment: expected TOML files or folders holding "
                         f"{DEPLOYMENT_TOML}", ", ".join(map(str, paths)))
    return sorted(found, key=lambda d: d.name), notes


def _sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def input_files(config: Path) -> list[Path]:
    """The deployment's TOML and every file it names (a ROS 2 bag directory's files), or the
    TOML alone when it cannot be read (the task will fail and say why)."""
    try:
        cfg = load_config(config)
    except RtsgtError:
        return [config]
    paths = [config, *(s.file for s in cfg.stations if s.file is not None), cfg.gcp.file,
             cfg.reference.file]
    if cfg.weather is not None:
        paths.append(cfg.weather.file)
    if cfg.query_times is not None:
        paths.append(cfg.query_times)
    if cfg.measurements is not None:
        bag = cfg.measurements.file
        paths += sorted(p for p in bag.rglob("*") if p.is_file()) if bag.is_dir() else [bag]
    return list(dict.fromkeys(Path(p) for p in paths))


def input_fingerprint(config: Path) -> dict[str, str]:
    """SHA-256 of each of :func:`input_files`, by absolute path: what a complete run must
    have been made from to be skipped."""
    return {str(p): _sha256(p) for p in input_files(config) if p.is_file()}


def make_tasks(deployments: Sequence[Deployment], out: Path, *, base_seed: int = 0,
               options: dict | None = None, force: bool = False,
               report: bool = False) -> list[BatchTask]:
    """One task per deployment, its run directory ``out/<name>``, its seed and the inputs
    its ``summary.json`` will record."""
    options = dict(sorted((options or {}).items()))
    tasks = []
    for d in deployments:
        inputs = {"config": str(d.config), "files_sha256": input_fingerprint(d.config),
                  "batch": {"base_seed": int(base_seed), "options": options}}
        tasks.append(BatchTask(d.name, d.config, Path(out) / d.name,
                               deployment_seed(base_seed, d.name), options, inputs, force,
                               report))
    return tasks


def is_complete(task: BatchTask) -> bool:
    """Whether ``task``'s deployment is done already (docs/batch.md#resuming)."""
    if not complete_output(task.out, "run"):
        return False
    if task.report and not (task.out / "report.html").is_file():
        return False  # asked for the report, which this run lacks: run it again
    try:
        summary = read_summary(task.out)
    except InputError:
        return False
    doc = summary.document
    recorded = json.loads(json.dumps(doc.get("inputs", {})))
    return (summary.exists and summary.options.seed == task.seed
            and recorded == json.loads(json.dumps(task.inputs)))


def run_task(task: BatchTask) -> Outcome:
    """Run one deployment as ``rtsgt run`` does; never raises for the deployment's own
    problems: they are a ``"failed"`` :class:`Outcome` with a one-line message.

    The run's warnings are not shown (``summary.json`` records them).
    """
    t0 = time.perf_counter()
    message = ""
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            run_deployment(task.config, task.out, options=run_options(task.options),
                           profile=task.options.get("profile"), seed=task.seed,
                           force=task.force or task.out.exists(), report=task.report,
                           inputs=task.inputs)
    except RtsgtError as exc:
        message = _one_line(exc)
    except Exception as exc:  # a bug: this deployment fails, the others go on
        message = (f"unexpected {type(exc).__name__} inside rtsgt: {_one_line(exc)} (a bug: "
                   "please report it; `rtsgt run` on this deployment with RTSGT_TRACEBACK=1 "
                   "shows the traceback)")
    status = "failed" if message else "done"
    return Outcome(task.name, status, task.seed, task.out, task.config, message,
                   time.perf_counter() - t0)


def run_options(given: dict) -> dict:
    """The changes to a deployment's options (:meth:`RunOptions.updated
    <rtsgt.options.RunOptions.updated>`'s names) of a task's command-line ``options``
    (``rtsgt run``'s names: ``rate`` is ``rate_hz``; ``profile`` apart)."""
    return {("rate_hz" if k == "rate" else k): v for k, v in given.items() if k != "profile"}


def _one_line(exc: BaseException) -> str:
    return " ".join(str(exc).split()) or type(exc).__name__


def skipped(task: BatchTask) -> Outcome:
    """The outcome of a deployment already complete."""
    return Outcome(task.name, "skipped", task.seed, task.out, task.config)


def default_workers(n_tasks: int) -> int:
    """Workers of the default local cluster: the machine's CPUs (those this process may
    use), at most one per task and one per :data:`MEMORY_PER_WORKER` of memory."""
    cpus = available_cores()
    try:
        memory = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    except (ValueError, OSError, AttributeError):  # pragma: no cover - not POSIX
        memory = cpus * MEMORY_PER_WORKER
    return max(1, min(cpus, n_tasks, memory // MEMORY_PER_WORKER))


def dask_client(*, scheduler: str | None = None, workers: int | None = None,
                n_tasks: int = 1):
    """A ``dask.distributed.Client``: of the scheduler at ``scheduler``, or of a local
    cluster of ``workers`` processes (default :func:`default_workers`), one thread each.
    Close it (and its cluster) after use.

    Raises
    ------
    InputError
        Dask is not installed, or the scheduler cannot be reached.
    """
    try:
        import dask
        from dask.distributed import Client, LocalCluster
    except ImportError:
        raise InputError("rtsgt batch runs the deployments on Dask, which is not installed: "
                         "pip install 'rtsgt[batch]' (or run them one after the other with "
                         "--serial)") from None
    if scheduler is not None:
        try:
            return Client(scheduler, timeout="30s")
        except (OSError, TimeoutError) as exc:
            raise InputError(f"cannot reach the Dask scheduler at {scheduler}: "
                             f"{_one_line(exc)}") from None
    n = workers if workers is not None else default_workers(n_tasks)
    # the nanny's MALLOC_TRIM_THRESHOLD_ fixes glibc's mmap threshold, and every large array
    # is then mapped and unmapped anew: a run took 1.8x as long (docs/batch.md#dask)
    with dask.config.set({f"{NANNY_ENVIRON}.MALLOC_TRIM_THRESHOLD_": None}):
        cluster = LocalCluster(n_workers=n, threads_per_worker=1, processes=True,
                               dashboard_address=None)
    return Client(cluster)


def close_client(client) -> None:
    """Close a client of :func:`dask_client` and the local cluster it started, if any."""
    cluster = client.cluster
    client.close()
    if cluster is not None:
        cluster.close()


def run_batch(tasks: Sequence[BatchTask], *, client_factory: Callable | None = None,
              on_outcome: Callable[[Outcome], None] | None = None) -> list[Outcome]:
    """Run the tasks whose deployment is not complete (the others are skipped): on the
    workers of the Dask client that ``client_factory(number of tasks to run)`` makes (e.g.
    :func:`dask_client`; started only if there is something to run, closed at the end), or,
    without one, one after the other in this process. ``on_outcome`` is called with each
    outcome as it comes (the skipped ones first); returns the outcomes in the tasks' order."""
    say = on_outcome or (lambda o: None)
    outcomes: dict[str, Outcome] = {}
    todo = []
    for task in tasks:
        if not task.force and is_complete(task):
            outcomes[task.name] = skipped(task)
            say(outcomes[task.name])
        else:
            todo.append(task)
    if todo and client_factory is not None:
        client = client_factory(len(todo))
        try:
            for outcome in _run_on_dask(client, todo):
                outcomes[outcome.name] = outcome
                say(outcome)
        finally:
            close_client(client)
    else:
        for task in todo:
            outcomes[task.name] = run_task(task)
            say(outcomes[task.name])
    return [outcomes[t.name] for t in tasks]


def _run_on_dask(client, tasks: Sequence[BatchTask]):
    """The outcomes of ``tasks`` run on the client's workers, as they complete."""
    from dask.distributed import as_completed  # the client exists: dask is installed

    futures = {client.submit(run_task, task, pure=False,
                             key=f"rtsgt-batch-{task.name}-{secrets.token_hex(4)}"): task
               for task in tasks}
    for future in as_completed(futures):
        task = futures[future]
        try:
            outcome = future.result()
        except Exception as exc:  # the worker died, or the task was not delivered
            outcome = Outcome(task.name, "failed", task.seed, task.out, task.config,
                              f"the Dask task failed: {type(exc).__name__}: {_one_line(exc)}")
        yield outcome
