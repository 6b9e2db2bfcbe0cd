"""em-bench planners on a dask.distributed cluster (``--dask ADDRESS``).

The same trials as the local worker pool (:func:`em_exploration_ros.tools.bench.run_trials`),
submitted as dask tasks instead of worker processes: each task runs one trial on a worker
and returns its record; this process writes the record where the local pool's worker would
have written it. Results, resuming and failure records are therefore the same; only the
place a trial runs changes, and the workers need no access to ``--out``.

``ADDRESS`` is ``local:N`` (a ``LocalCluster`` of N single-threaded worker processes on this
machine, closed at the end) or a scheduler address such as ``tcp://host:8786`` (a running
cluster: ``dask scheduler`` on one host, ``dask worker tcp://host:8786 --nthreads 1`` on
each worker host, every worker with this project installed at the same code version).
"""
from __future__ import annotations

import logging
import re
import signal
import time
import uuid
from contextlib import contextmanager
from typing import Any, Iterator, Sequence

from distributed import Client, LocalCluster, as_completed

from em_exploration_ros.tools import bench_trials

_LOG = logging.getLogger("em-bench")

_LOCAL = re.compile(r"local:(\d+)")


def parse_address(address: str) -> int | str:
    """The number of local workers of ``local:N`` (N >= 1), else the scheduler address
    (``scheme://host:port``); ValueError for anything else."""
    local = _LOCAL.fullmatch(address)
    if local:
        workers = int(local.group(1))
        if workers < 1:
            raise ValueError("--dask local:N needs at least one worker")
        return workers
    if not re.fullmatch(r"[a-z][a-z0-9+]*://\S+", address):
        raise ValueError(f"--dask expects local:N or a scheduler address like "
                         f"tcp://host:8786, got {address!r}")
    return address


@contextmanager
def connect(address: str) -> Iterator[Client]:
    """A client of the cluster named by ``address`` (see :func:`parse_address`); a local
    cluster is started here and shut down on exit."""
    target = parse_address(address)
    # dask's own start-up and shut-down chatter (INFO) would bury em-bench's progress.
    logging.getLogger("distributed").setLevel(logging.WARNING)
    if isinstance(target, int):
        # One thread per worker process: a trial is Python + GTSAM and holds the GIL.
        with _workers_ignoring_ctrl_c():
            cluster = LocalCluster(n_workers=target, threads_per_worker=1, processes=True,
                                   dashboard_address=None)
        with cluster, Client(cluster) as client:
            yield client
    else:
        with Client(target) as client:
            yield client


@contextmanager
def _workers_ignoring_ctrl_c() -> Iterator[None]:
    """SIGINT ignored while the local cluster starts its worker processes, which keep that
    disposition (Python installs its KeyboardInterrupt handler only over the default one):
    Ctrl-C reaches the whole process group, and workers that took it would die printing
    tracebacks while em-bench itself stops them in order. A Ctrl-C during the cluster's
    start-up is ignored with them."""
    previous = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)


def worker_slots(client: Client) -> int:
    """Number of trials the cluster runs at once (its worker threads, at least 1)."""
    return max(1, sum(client.nthreads().values()))


def checked_trial_record(spec: bench_trials.TrialSpec) -> dict[str, Any]:
    """Task body: the trial's record, or a failed one if this worker runs other code than
    the submitting checkout (both versions known and different)."""
    here = bench_trials.code_version()
    if "unknown" not in (here, spec.code_version) and here != spec.code_version:
        return bench_trials.failed_record(spec, f"worker runs code version {here}, not "
                                   f"{spec.code_version}", 0.0)
    return bench_trials.trial_record(spec)


def run_on_cluster(client: Client, specs: Sequence[bench_trials.TrialSpec],
                   progress: bench_trials.ProgressBar) -> None:
    """Run every trial on the cluster and write each record as it arrives, where the
    local pool's worker would have written it; a task the cluster loses (e.g. its worker
    died: ``KilledWorker``) gets a failed record. Tasks not finished when this returns
    (Ctrl-C) are cancelled.

    ``progress`` learns a trial started when a slot should be free for it: dask does not
    report when a task starts, and it runs them roughly in submission order.
    """
    progress.queue(specs)
    slots = worker_slots(client)
    _LOG.info("dask cluster %s: %d worker thread(s)", client.scheduler.address, slots)
    spec_of = {}
    submitted = time.perf_counter()
    for spec in specs:
        spec.path.unlink(missing_ok=True)
        # A unique key: another em-bench on a shared cluster may run the same seed with
        # other parameters, and dask would hand it this task's result under an equal key.
        key = f"em-trial-{spec.setting}-{spec.planner}-{spec.seed}-{uuid.uuid4().hex}"
        future = client.submit(checked_trial_record, spec, pure=False, key=key)
        spec_of[future.key] = (future, spec)
    waiting = list(specs)
    try:
        for spec in waiting[:slots]:
            progress.started(spec)
        del waiting[:slots]
        for future in as_completed([future for future, _ in spec_of.values()]):
            spec = spec_of[future.key][1]
            try:
                record = future.result()
            except Exception as error:  # noqa: BLE001 - a lost task is a failed trial
                record = bench_trials.failed_record(spec, "dask task lost: "
                                             + bench_trials.describe_error(error),
                                             time.perf_counter() - submitted)
            bench_trials.write_json(spec.path, record)
            progress.finished(spec, record)
            if waiting:
                progress.started(waiting.pop(0))
    finally:
        client.cancel([future for future, _ in spec_of.values()])
        progress.close()
