"""em-bench planners on a dask.distributed cluster: the same records as the local worker
pool, resuming, and refusal of a bad address."""
import json
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from em_exploration_ros.tools.bench_dask import parse_address
from process_tree import alive, descendants, interruptible
from ros_process import wait_until

REPO = Path(__file__).resolve().parents[1]
# Two nearest-frontier trials on a small map, and two on a 12 m map where the world
# generator fails.
TRIALS = ["planners", "--planners", "NEAREST", "--landmarks", "4", "--trials", "2",
          "--max-steps", "800", "--map-size", "40", "12", "--cell-size", "2", "2"]
#: Summary entries that measure the host, not the exploration.
HOST_TIMES = ("wall_s", "decision_time_median_s", "decision_time_max_s")


def run_cli(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "em_exploration_ros.tools.bench", *args],
                          cwd=REPO, capture_output=True, text=True, timeout=300, check=False)


def exploration_record(path: Path) -> dict:
    """A trial record without the host's timings."""
    record = json.loads(path.read_text())
    record.pop("wall_s")
    record.pop("traceback", None)
    summary = record.get("summary")
    if summary is not None:
        for key in HOST_TIMES:
            summary.pop(key)
        for robot in summary["robots"]:
            robot.pop("decision_times_s")
    return record


@pytest.fixture(scope="module")
def pool_and_dask(tmp_path_factory) -> tuple[Path, Path, str]:
    pool = tmp_path_factory.mktemp("pool")
    dask = tmp_path_factory.mktemp("dask")
    result = run_cli(*TRIALS, "--jobs", "2", "--out", str(pool))
    assert result.returncode == 0, result.stderr
    result = run_cli(*TRIALS, "--dask", "local:2", "--out", str(dask))
    assert result.returncode == 0, result.stderr
    return pool, dask, result.stderr


def test_dask_cluster_writes_the_records_of_the_local_pool(pool_and_dask):
    pool, dask, log = pool_and_dask
    assert "4 trials: 0 finished earlier, 4 to run on dask cluster local:2" in log
    assert "2 worker thread(s)" in log
    statuses = []
    for path in sorted((pool / "trials").glob("*/*/seed_*.json")):
        mine = exploration_record(dask / path.relative_to(pool))
        assert mine == exploration_record(path)
        statuses.append(mine["status"])
    assert statuses == ["failed", "failed", "done", "done"]  # 12m_cell2m, then 40m_cell2m
    record = exploration_record(dask / "trials/40m_cell2m/NEAREST/seed_1.json")
    assert record["summary"]["decisions"] > 0
    assert (dask / "results.csv").read_text() == (pool / "results.csv").read_text()


def test_dask_rerun_runs_only_what_is_missing(pool_and_dask):
    _, dask, _ = pool_and_dask
    done = dask / "trials/40m_cell2m/NEAREST/seed_0.json"
    before = done.read_text()
    (dask / "trials/40m_cell2m/NEAREST/seed_1.json").unlink()
    result = run_cli(*TRIALS, "--dask", "local:1", "--out", str(dask))
    assert result.returncode == 0, result.stderr
    # The failed trials are retried, the missing one is run, the finished one is kept.
    assert "4 trials: 1 finished earlier, 3 to run on dask cluster local:1" in result.stderr
    assert done.read_text() == before
    summary = json.loads((dask / "summary.json").read_text())
    assert summary["last_invocation"]["ran"] == 3
    assert summary["settings"]["40m_cell2m"]["planners"]["NEAREST"]["trials_done"] == 2


def test_ctrl_c_on_a_local_cluster_stops_it_without_tracebacks(tmp_path):
    """Ctrl-C reaches the local cluster's worker processes too: they must not die printing
    tracebacks while em-bench stops the cluster; em-bench reports the interruption (exit
    code 130) and leaves no process behind."""
    command = [sys.executable, "-m", "em_exploration_ros.tools.bench", "planners",
               "--planners", "CE", "--landmarks", "4", "--trials", "2", "--max-steps", "3000",
               "--map-size", "60", "--cell-size", "2", "--dask", "local:2",
               "--out", str(tmp_path)]
    bench_process = subprocess.Popen(command, cwd=REPO, stderr=subprocess.PIPE, text=True,
                                     start_new_session=True, preexec_fn=interruptible)
    lines: list[str] = []
    reader = threading.Thread(target=lambda: lines.extend(bench_process.stderr), daemon=True)
    reader.start()
    try:
        wait_until(lambda: any("worker thread(s)" in line for line in lines)
                   or bench_process.poll() is not None, 90.0, "the cluster's workers")
        assert bench_process.poll() is None, lines
        time.sleep(1.0)  # into the trials
        cluster = descendants(bench_process.pid)
        os.killpg(bench_process.pid, signal.SIGINT)
        bench_process.wait(timeout=60)
    finally:
        bench_process.kill()
    reader.join(timeout=10)
    stderr = "".join(lines)
    assert bench_process.returncode == 130, stderr
    assert "interrupted; finished trials are kept, rerun to resume" in stderr
    assert "Traceback" not in stderr and "KeyboardInterrupt" not in stderr, stderr
    assert "distributed.scheduler" not in stderr  # dask's INFO chatter stays out
    assert len(cluster) >= 2  # the two workers at least
    wait_until(lambda: not any(alive(pid) for pid in cluster), 10.0,
               "the cluster's processes to end")
    assert not any(alive(pid) for pid in cluster)


@pytest.mark.parametrize("address", ["local:0", "local:x", "8786", "host:8786"])
def test_bad_dask_addresses_are_refused(address):
    with pytest.raises(ValueError, match="--dask"):
        parse_address(address)


def test_em_bench_refuses_a_bad_dask_address_before_running(tmp_path):
    result = run_cli(*TRIALS, "--dask", "host:8786", "--out", str(tmp_path))
    assert result.returncode == 2 and "--dask expects" in result.stderr
    assert not (tmp_path / "trials").exists()


def test_good_dask_addresses_parse():
    assert parse_address("local:2") == 2
    assert parse_address("tcp://10.0.0.5:8786") == "tcp://10.0.0.5:8786"
