"""Tests of em-bench: a short planner comparison through the real CLI, resuming, re-plotting,
failed trials, and the progress/ETA bookkeeping."""
import csv
import dataclasses
import io
import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import pytest

from em_exploration_ros.core.params import ExplorationParams
from em_exploration_ros.tools import bench, bench_plots, bench_trials, math_platform
from openblas_cores import other_core_type
from process_tree import alive, children, command_line, interruptible
from ros_process import wait_until

REPO = Path(__file__).resolve().parents[1]
PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
# Two settings: a small map, and a 12 m map too small for the world generator (start poses
# and 4 landmarks 10 m apart), so every trial of it fails while the others finish.
SHORT_RUN = ["planners", "--planners", "NEAREST", "CE", "--landmarks", "4", "--trials", "2",
             "--jobs", "2", "--max-steps", "1500"]
GOOD = ["--map-size", "40", "--cell-size", "2"]
GOOD_AND_BAD = ["--map-size", "40", "12", "--cell-size", "2", "2"]


def run_cli(*args: str, env: dict[str, str] | None = None) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "em_exploration_ros.tools.bench", *args],
                          cwd=REPO, capture_output=True, text=True, timeout=300, check=False,
                          env=env)


@pytest.fixture(scope="module")
def bench_run(tmp_path_factory) -> tuple[Path, subprocess.CompletedProcess]:
    out = tmp_path_factory.mktemp("bench")
    result = run_cli(*SHORT_RUN, *GOOD_AND_BAD, "--out", str(out))
    assert result.returncode == 0, result.stderr
    return out, result


@pytest.fixture(scope="module")
def bench_out(bench_run) -> Path:
    return bench_run[0]


def test_trials_from_the_fork_server_print_no_warning(bench_run):
    """Each trial re-runs the main module (here ``python -m ...bench``); the fork server
    must not have imported it already, or every trial warns that it was."""
    assert "Warning" not in bench_run[1].stderr, bench_run[1].stderr


def test_every_trial_has_a_record(bench_out):
    for setting, status in (("40m_cell2m", "done"), ("12m_cell2m", "failed")):
        for planner in ("NEAREST", "CE"):
            for seed in (0, 1):
                record = json.loads(
                    (bench_out / "trials" / setting / planner / f"seed_{seed}.json").read_text())
                assert record["status"] == status
                assert (record["setting"], record["planner"], record["seed"]) == (
                    setting, planner, seed)
    failed = json.loads((bench_out / "trials/12m_cell2m/CE/seed_0.json").read_text())
    assert failed["error"].startswith("ValueError: cannot place 3 robots")
    assert "Traceback" in failed["traceback"]


def test_csv_has_one_row_per_history_sample(bench_out):
    with (bench_out / "results.csv").open(newline="") as stream:
        rows = list(csv.reader(stream))
    assert tuple(rows[0]) == bench_plots.CSV_COLUMNS
    expected = 0
    for planner in ("NEAREST", "CE"):
        for seed in (0, 1):
            record = json.loads(
                (bench_out / "trials/40m_cell2m" / planner / f"seed_{seed}.json").read_text())
            history = record["summary"]["history"]
            trial_rows = [r for r in rows[1:] if r[1] == planner and r[2] == str(seed)]
            assert len(trial_rows) == len(history) > 5
            assert float(trial_rows[-1][3]) == pytest.approx(record["summary"]["distance_m"])
            distances = [float(r[3]) for r in trial_rows]
            assert distances == sorted(distances)
            expected += len(history)
    assert len(rows) - 1 == expected
    assert {r[0] for r in rows[1:]} == {"40m_cell2m"}


def test_summary_json_has_counts_finals_and_paired_differences(bench_out):
    summary = json.loads((bench_out / "summary.json").read_text())
    good, bad = summary["settings"]["40m_cell2m"], summary["settings"]["12m_cell2m"]
    assert good["map_size_m"] == [40.0, 40.0] and good["cell_size_m"] == 2.0
    assert good["num_landmarks"] == 4 and good["num_robots"] == 3
    for planner in ("NEAREST", "CE"):
        entry = good["planners"][planner]
        assert (entry["trials_done"], entry["trials_failed"]) == (2, 0)
        assert set(entry["final"]) == set(bench.FINAL_METRICS)
        explored = entry["final"]["explored_ratio"]
        assert explored["n"] == 2 and 0.0 < explored["mean"] <= 1.0 and explored["ci95"] >= 0
        assert entry["final"]["loc_rmse_m"]["mean"] > 0.0
        assert entry["wall_s_total"] > 0.0
        activity = entry["activity"]
        assert sum(activity["decisions_by_type"].values()) > 0
        assert set(activity["rendezvous"]) == {"requested", "met", "timed_out", "open"}
        assert activity["slam_recoveries"] == 0
        assert len(entry["code_versions"]) == 1
        assert (bad["planners"][planner]["trials_done"],
                bad["planners"][planner]["trials_failed"]) == (0, 2)
    pairs = {(d["a"], d["b"], d["metric"]) for d in good["paired_differences"]}
    assert pairs == {("CE", "NEAREST", m) for m in bench.PAIRED_METRICS}
    assert summary["last_invocation"]["ran"] == 8


def test_plots_and_markdown_are_written(bench_out):
    for suffix in ("loc_rmse", "landmark_rmse", "explored_ratio"):
        png = (bench_out / f"40m_cell2m_{suffix}.png").read_bytes()
        assert png.startswith(PNG_SIGNATURE) and len(png) > 10_000
    assert not list(bench_out.glob("12m_cell2m_*.png"))
    markdown = (bench_out / "results.md").read_text()
    assert "| NEAREST | 2 (0) |" in markdown and "| CE | 2 (0) |" in markdown
    assert "| CE − NEAREST |" in markdown
    assert "| open | SLAM re-solves |" in markdown
    assert "![40m_cell2m_loc_rmse](40m_cell2m_loc_rmse.png)" in markdown
    assert "NEAREST seed 1: `ValueError" in markdown


def test_rerun_skips_finished_trials_and_plot_remakes_outputs(bench_out):
    csv_before = (bench_out / "results.csv").read_text()
    result = run_cli(*SHORT_RUN, *GOOD, "--out", str(bench_out))
    assert result.returncode == 0, result.stderr
    assert "4 trials: 4 finished earlier, 0 to run" in result.stderr
    summary = json.loads((bench_out / "summary.json").read_text())
    assert summary["last_invocation"]["ran"] == 0
    assert summary["last_invocation"]["finished_earlier"] == 4
    assert (bench_out / "results.csv").read_text() == csv_before

    for png in bench_out.glob("*.png"):
        png.unlink()
    (bench_out / "results.md").unlink()
    result = run_cli("plot", "--out", str(bench_out))
    assert result.returncode == 0, result.stderr
    assert len(list(bench_out.glob("40m_cell2m_*.png"))) == 3
    assert "| CE | 2 (0) |" in (bench_out / "results.md").read_text()


def test_records_name_the_numerical_kernels_they_ran_on(bench_out):
    here = math_platform.describe()
    for planner in ("NEAREST", "CE"):
        record = json.loads((bench_out / "trials/40m_cell2m" / planner / "seed_1.json")
                            .read_text())
        assert record["math_platform"] == here
    summary = json.loads((bench_out / "summary.json").read_text())
    for entry in summary["settings"]["40m_cell2m"]["planners"].values():
        assert entry["math_platforms"] == [here]
    assert summary["settings"]["12m_cell2m"]["planners"]["CE"]["math_platforms"] == []
    assert bench.mixed_provenance(summary) == []
    assert f"Their numerical kernels: {here}." in (bench_out / "results.md").read_text()


@pytest.mark.skipif(other_core_type() is None,
                    reason="the OpenBLAS core types forced here exist on x86_64 only")
def test_a_trial_rerun_on_other_kernels_is_flagged(bench_out, tmp_path):
    """A resumed run (or a cluster) whose trials ran on other SIMD kernels: every record
    keeps its own, and em-bench warns that the setting mixes them. The rerun forces an
    OpenBLAS core other than this process's (its preset OPENBLAS_CORETYPE, if any, and the
    core its OpenBLAS reports), whatever the host presets."""
    host_core = math_platform.openblas_core()
    core_type, core_name = other_core_type(os.environ.get("OPENBLAS_CORETYPE"), host_core)
    out = tmp_path / "out"
    shutil.copytree(bench_out, out)
    (out / "trials/40m_cell2m/CE/seed_0.json").unlink()
    result = run_cli(*SHORT_RUN, *GOOD, "--out", str(out),
                     env={**os.environ, "OPENBLAS_CORETYPE": core_type})
    assert result.returncode == 0, result.stderr
    assert "4 trials: 3 finished earlier, 1 to run" in result.stderr
    rerun = json.loads((out / "trials/40m_cell2m/CE/seed_0.json").read_text())
    assert rerun["status"] == "done"
    assert rerun["math_platform"].endswith(f"; OPENBLAS_CORETYPE={core_type}")
    assert f"OpenBLAS core {core_name};" in rerun["math_platform"]
    assert f"OpenBLAS core {host_core};" not in rerun["math_platform"]
    summary = json.loads((out / "summary.json").read_text())
    planners = summary["settings"]["40m_cell2m"]["planners"]
    assert planners["CE"]["math_platforms"] == sorted([math_platform.describe(),
                                                       rerun["math_platform"]])
    assert planners["NEAREST"]["math_platforms"] == [math_platform.describe()]
    assert "40m_cell2m: the finished trials ran on 2 sets of numerical kernels" in result.stderr


def test_a_setting_that_mixes_code_versions_is_named(bench_out):
    summary = json.loads((bench_out / "summary.json").read_text())
    entry = summary["settings"]["40m_cell2m"]["planners"]["CE"]
    here = entry["code_versions"][0]
    entry["code_versions"] = versions = sorted([here, "0123abc"])
    assert bench.mixed_provenance(summary) == [
        f"40m_cell2m: the finished trials ran 2 code versions ({versions[0]} | {versions[1]});"
        " their results may differ for that reason alone"]


def test_unusable_records_are_reported_and_run_again(bench_out, tmp_path):
    out = tmp_path / "out"
    shutil.copytree(bench_out, out)
    trials = out / "trials/40m_cell2m"
    (trials / "NEAREST/seed_0.json").write_bytes(b"\x89 not JSON")
    edited = json.loads((trials / "CE/seed_1.json").read_text())
    del edited["summary"]["history"]
    (trials / "CE/seed_1.json").write_text(json.dumps(edited))
    (trials / "NEAREST/seed_1.json").unlink()
    os.mkfifo(trials / "NEAREST/seed_1.json")  # reading it would block for ever
    with (trials / "CE/seed_0.json").open("r+b") as record:  # sparse: 17 MiB on paper
        record.truncate(bench.MAX_RECORD_BYTES + 1024 * 1024)
    result = run_cli(*SHORT_RUN, *GOOD, "--out", str(out))
    assert result.returncode == 0, result.stderr
    assert "NEAREST/seed_0.json is not a usable trial record: unreadable" in result.stderr
    assert ("CE/seed_1.json is not a usable trial record: its history is not a list of "
            "samples") in result.stderr
    assert "NEAREST/seed_1.json is not a usable trial record: not a regular file" \
        in result.stderr
    assert (f"CE/seed_0.json is not a usable trial record: {bench.MAX_RECORD_BYTES + 2 ** 20} "
            f"bytes, more than a trial record's {bench.MAX_RECORD_BYTES} at most"
            ) in result.stderr
    assert "4 trials: 0 finished earlier, 4 to run" in result.stderr
    for path in trials.glob("*/seed_*.json"):
        record = json.loads(path.read_text())
        assert record["status"] == "done" and bench.record_problem(record) is None


def _break(record: dict, path: str, value: object) -> dict:
    """``record`` with the item at ``path`` (keys joined by '/') set to ``value``, or
    removed when ``value`` is ``KeyError``."""
    *parents, last = path.split("/")
    container = record
    for key in parents:
        container = container[int(key)] if isinstance(container, list) else container[key]
    if value is KeyError:
        del container[last]
    else:
        container[last] = value
    return record


@pytest.mark.parametrize("path, value, problem", [
    ("status", "running", "its status is neither done nor failed"),
    ("seed", "0", "no seed"),
    ("params/run", KeyError, "its params lack world, map or run"),
    ("summary/distance_m", "far", "its summary lacks a final value"),
    ("summary/loc_rmse_m", True, "its summary lacks a final value"),
    ("summary/history/0/explored_ratio", KeyError, "its history is not a list of samples"),
])
def test_record_problems_are_named(bench_out, path, value, problem):
    record = json.loads((bench_out / "trials/40m_cell2m/CE/seed_0.json").read_text())
    assert bench.record_problem(record) is None
    assert bench.record_problem(_break(record, path, value)) == problem
    failed = json.loads((bench_out / "trials/12m_cell2m/CE/seed_0.json").read_text())
    assert bench.record_problem(failed) is None
    assert bench.record_problem(_break(failed, "error", KeyError)) == (
        "a failed trial without its error")


def test_a_folder_in_the_place_of_a_record_is_refused_before_any_trial(tmp_path):
    """A trial's old record is removed before the trial runs; a folder there could not be,
    so it is named before any trial starts instead of failing the run midway."""
    in_the_way = tmp_path / "trials/40m_cell2m/CE/seed_1.json"
    in_the_way.mkdir(parents=True)
    result = run_cli(*SHORT_RUN, *GOOD, "--out", str(tmp_path))
    assert result.returncode == 2, result.stderr
    assert (f"{in_the_way} is a folder where the record of trial 40m_cell2m/CE/seed 1 goes; "
            "remove it") in result.stderr
    assert "trials:" not in result.stderr and "Traceback" not in result.stderr


def test_an_out_folder_that_cannot_be_made_is_refused_before_any_trial(tmp_path):
    a_file = tmp_path / "a_file"
    a_file.write_text("")
    below = a_file / "below"
    for out, message in ((a_file, f"--out {a_file} is not a folder"),
                         (below, f"--out {below}: cannot create the folder (Not a directory)")):
        result = run_cli(*SHORT_RUN, *GOOD, "--out", str(out))
        assert result.returncode == 2 and message in result.stderr, result.stderr
        assert "trials:" not in result.stderr and "Traceback" not in result.stderr


def test_plot_refuses_results_it_did_not_write(bench_out, tmp_path, capsys):
    """Through em-bench's main in this process (one case through the CLI, for its exit
    code and stderr without a traceback)."""
    out = tmp_path / "out"
    shutil.copytree(bench_out, out)
    rows = (bench_out / "results.csv").read_text().splitlines()
    cases = [("{}", None, "summary.json: no settings"),
             ("not JSON", None, "Expecting value"),
             ('{"settings": {"x": 1}}', None, "setting x: not an object"),
             (None, rows[:2] + [rows[2] + ",7"], "results.csv: line 3 has 9 values, not 8"),
             (None, rows[:2] + [rows[2].replace("CE", "CE,x", 1)[:-2]], "results.csv: line 3"),
             (None, [], "results.csv: header [] is not")]
    refusal = f"cannot make the plots from {out}: its summary.json or results.csv is not as"
    for summary, csv_lines, problem in cases:
        shutil.copy(bench_out / "summary.json", out / "summary.json")
        shutil.copy(bench_out / "results.csv", out / "results.csv")
        if summary is not None:
            (out / "summary.json").write_text(summary)
        if csv_lines is not None:
            (out / "results.csv").write_text("\n".join(csv_lines) + "\n")
        assert bench.main(["plot", "--out", str(out)]) == 2
        error, hint = capsys.readouterr().err.splitlines()
        assert error.startswith(f"em-bench: error: {refusal}") and problem in error, error
        assert hint == "Try 'em-bench --help'."
    result = run_cli("plot", "--out", str(out))  # the last case
    assert result.returncode == 2 and refusal in result.stderr, result.stderr
    assert "Traceback" not in result.stderr


def _mutations(data, path=()):
    """Every copy of ``data`` with one part of it removed or of another type: (path, copy)."""
    if isinstance(data, dict):
        children = list(data.items())
    elif isinstance(data, list):
        children = list(enumerate(data))
    else:
        return
    for key, value in children:
        for replacement in ("removed", "x", None, [], {}, 1.5, True, [None]):
            copy = json.loads(json.dumps(data))
            if replacement == "removed":
                del copy[key]
            else:
                copy[key] = replacement
            yield (*path, key, replacement), copy
        for sub_path, sub_copy in _mutations(value, (*path, key)):
            copy = json.loads(json.dumps(data))
            copy[key] = sub_copy
            yield sub_path, copy


def test_the_summary_check_covers_what_results_md_reads(bench_out):
    """For every part of a real summary.json removed or given another type, either
    ``summary_problem`` names a problem, or results.md is made from it without an error:
    what the check lets through never breaks the report."""
    summary = json.loads((bench_out / "summary.json").read_text())
    assert bench_plots.summary_problem(summary) is None
    refused = made = 0
    for path, mutated in _mutations(summary):
        if bench_plots.summary_problem(mutated) is not None:
            refused += 1
            continue
        try:
            bench_plots.results_markdown(mutated, {})
        except Exception as error:  # noqa: BLE001 - reported with the mutation that did it
            pytest.fail(f"{path}: passed the check, then {error!r}")
        made += 1
    assert refused > 100 and made > 100, (refused, made)


def test_plot_does_not_pass_a_bug_off_as_bad_input(bench_out, tmp_path):
    """Only what bench_plots names as not as em-bench writes it is reported as bad input;
    an error of the plotting code itself is raised as it is."""
    out = tmp_path / "out"
    shutil.copytree(bench_out, out)

    def broken_plot(*args, **kwargs):
        raise KeyError("a bug")

    with pytest.raises(KeyError, match="a bug"):
        bench.command_plot(bench.build_parser().parse_args(["plot", "--out", str(out)]),
                           plot=broken_plot)


def test_rerun_with_other_parameters_is_refused(bench_out):
    result = run_cli(*SHORT_RUN, *GOOD, "--robots", "2", "--out", str(bench_out))
    assert result.returncode == 2
    assert "other parameters" in result.stderr


def test_bad_arguments_are_rejected(tmp_path):
    result = run_cli("planners", "--map-size", "40", "100", "--cell-size", "2",
                     "--out", str(tmp_path))
    assert result.returncode == 2 and "one value per map size" in result.stderr
    result = run_cli("planners", "--planners", "XX", "--out", str(tmp_path))
    assert result.returncode == 2 and "invalid choice" in result.stderr
    result = run_cli("planners", "--trials", "0", "--out", str(tmp_path))
    assert result.returncode == 2 and "--trials must be at least 1, got 0" in result.stderr


def test_trial_specs_follow_the_paper_defaults(tmp_path):
    args = bench.build_parser().parse_args(
        ["planners", "--map-size", "100", "200", "--trials", "3", "--seed-start", "5",
         "--max-distance", "1400", "--out", str(tmp_path)])
    specs = bench.trial_specs(args, tmp_path)
    assert len(specs) == 2 * 3 * len(bench.PAPER_PLANNERS)
    assert {s.setting for s in specs} == {"100m_cell2m", "200m_cell4m"}
    assert {s.seed for s in specs} == {5, 6, 7}
    first = specs[0].params
    assert first.map.cell_size_m == 2.0 and first.run.max_distance_m == 1400.0
    # same seed, same world under every planner; the seed is the only difference
    same_seed = [s.params for s in specs if s.setting == "100m_cell2m" and s.seed == 6]
    assert [p.planner.name for p in same_seed] == list(bench.PAPER_PLANNERS)
    assert len({(p.world, p.sensors, p.run) for p in same_seed}) == 1


def test_error_description_is_one_short_line():
    error = RuntimeError("\nIndeterminate linear system\n\nnear variable b62." + " x" * 200)
    text = bench_trials.describe_error(error)
    assert text.startswith("RuntimeError: Indeterminate linear system near variable b62. x")
    assert "\n" not in text and len(text) == bench_trials.ERROR_CHARS and text.endswith("...")


def test_worker_that_dies_without_a_record_is_recorded_as_failed(tmp_path):
    spec = bench_trials.TrialSpec("s", "NEAREST", 3, ExplorationParams(), tmp_path / "seed_3.json")
    record = bench.record_after_exit(spec, -9, 12.5)
    assert record["status"] == "failed" and "code -9" in record["error"]
    assert bench.read_record(spec.path) == record
    spec = dataclasses.replace(spec, path=tmp_path / "seed_4.json", seed=4)
    lost = bench.record_after_exit(spec, bench.FORK_SERVER_LOST_EXIT_CODE, 3.0)
    assert "code 255" in lost["error"] and "fork server" in lost["error"]


#: Three trials of a few seconds each on two workers.
KILLED_SERVER_RUN = ["planners", "--planners", "CE", "--landmarks", "4", "--trials", "3",
                     "--jobs", "2", "--max-steps", "3000", "--map-size", "60",
                     "--cell-size", "2"]


def _two_running_workers(bench_pid: int) -> tuple[int, list[int]]:
    """em-bench's fork server and its two workers, once both have started (60 s at most)."""
    found: dict[str, Any] = {"server": None, "workers": []}

    def both_started() -> bool:
        found["server"] = next((child for child in children(bench_pid)
                                if b"forkserver" in command_line(child)), None)
        found["workers"] = children(found["server"]) if found["server"] else []
        return len(found["workers"]) == 2

    wait_until(both_started, 60.0, "the two first trials", poll_s=0.01)
    return found["server"], found["workers"]


def test_trials_of_a_killed_fork_server_are_stopped_failed_and_run_again(tmp_path):
    """SIGKILL of the fork server while two trials run: the two workers would outlive it
    and later overwrite their failed records; they are stopped, recorded as failed with
    the likely cause, the third trial starts from a new fork server, and a rerun finishes
    the two."""
    command = [sys.executable, "-m", "em_exploration_ros.tools.bench", *KILLED_SERVER_RUN,
               "--out", str(tmp_path)]
    bench_process = subprocess.Popen(command, cwd=REPO, stderr=subprocess.PIPE, text=True)
    try:
        server, workers = _two_running_workers(bench_process.pid)
        os.kill(server, signal.SIGKILL)
        stderr = bench_process.communicate(timeout=240)[1]
    finally:
        bench_process.kill()
    assert bench_process.returncode == 0, stderr
    assert not any(alive(worker) for worker in workers)
    assert stderr.count("outlived its fork server; stopping it") == 2, stderr
    assert stderr.count("exited with code 255 without a result (or the fork server it came "
                        "from died)") == 2, stderr
    records = [json.loads(path.read_text()) for path in tmp_path.glob("trials/*/*/*.json")]
    assert sorted(r["status"] for r in records) == ["done", "failed", "failed"]
    summary = json.loads((tmp_path / "summary.json").read_text())
    assert summary["settings"]["60m_cell2m"]["planners"]["CE"]["trials_failed"] == 2
    rerun = subprocess.run(command, cwd=REPO, capture_output=True, text=True, timeout=240,
                           check=False)
    assert rerun.returncode == 0 and "3 trials: 1 finished earlier, 2 to run" in rerun.stderr
    assert all(json.loads(path.read_text())["status"] == "done"
               for path in tmp_path.glob("trials/*/*/*.json"))


def test_ctrl_c_stops_every_trial_quietly_and_a_rerun_resumes(tmp_path):
    """Ctrl-C in a terminal sends SIGINT to em-bench, its fork server and its workers
    alike: em-bench says it was interrupted (exit code 130), no worker prints a traceback
    or outlives it, and a rerun runs the interrupted trials."""
    command = [sys.executable, "-m", "em_exploration_ros.tools.bench", *KILLED_SERVER_RUN,
               "--out", str(tmp_path)]
    bench_process = subprocess.Popen(command, cwd=REPO, stderr=subprocess.PIPE, text=True,
                                     start_new_session=True, preexec_fn=interruptible)
    try:
        server, workers = _two_running_workers(bench_process.pid)
        time.sleep(1.0)  # into their trials, past the fork server's start-up of a worker
        os.killpg(bench_process.pid, signal.SIGINT)
        stderr = bench_process.communicate(timeout=60)[1]
    finally:
        bench_process.kill()
    assert bench_process.returncode == 130, stderr
    assert "interrupted; finished trials are kept, rerun to resume" in stderr
    assert "Traceback" not in stderr and "KeyboardInterrupt" not in stderr, stderr
    wait_until(lambda: not any(alive(pid) for pid in (server, *workers)), 10.0,
               "the fork server and the workers to end")
    assert not any(alive(pid) for pid in (server, *workers))
    rerun = subprocess.run(command, cwd=REPO, capture_output=True, text=True, timeout=240,
                           check=False)
    assert rerun.returncode == 0, rerun.stderr
    assert all(json.loads(path.read_text())["status"] == "done"
               for path in tmp_path.glob("trials/*/*/*.json"))


def test_progress_reports_each_trial_and_estimates_time_left(tmp_path):
    now = [0.0]
    stream = io.StringIO()
    specs = [bench_trials.TrialSpec("s", planner, seed, ExplorationParams(),
                                    tmp_path / f"{seed}.json")
             for seed in (0, 1) for planner in ("NEAREST", "CE")]
    progress = bench_trials.ProgressBar(4, 2, stream, clock=lambda: now[0])
    progress.queue(specs)
    assert progress.eta_s() is None
    progress.started(specs[0])
    progress.started(specs[1])
    now[0] = 10.0
    progress.finished(specs[0], {"status": "done", "wall_s": 10.0,
                                 "summary": {"explored_ratio": 0.85, "distance_m": 120.0}})
    # pending NEAREST 10 s + CE (overall mean 10 s) + running CE (10 s expected, 10 s spent)
    assert progress.eta_s() == pytest.approx(10.0)
    progress.finished(specs[1], {"status": "failed", "wall_s": 30.0, "error": "KeyError: 1"})
    lines = stream.getvalue().splitlines()
    assert lines[0].startswith("[1/4] s/NEAREST/seed 0: done in 10.0 s (explored 0.850, 120 m)")
    assert lines[1].startswith("[2/4] s/CE/seed 0: FAILED after 30.0 s: KeyError: 1")
    assert "left ~0:00:20" in lines[1]


class _FakeWorker:
    """A worker process whose start fails as over a fork server that has just died."""

    def __init__(self, failures: list[BaseException]) -> None:
        self.name, self.started, self._failures = "trial", False, failures

    def start(self) -> None:
        if self._failures:
            raise self._failures.pop(0)
        self.started = True


def test_a_worker_whose_fork_server_just_died_is_started_again():
    """SIGKILL of the fork server just before a start: multiprocessing still takes the server
    for alive and the start fails reading the pid (a CI run ended em-bench with an EOFError
    traceback); the next try starts a new server."""
    failures: list[BaseException] = [EOFError("unexpected EOF"), ConnectionResetError()]
    made: list[_FakeWorker] = []
    started = bench.start_worker(lambda: made.append(_FakeWorker(failures)) or made[-1],
                                 retry_s=0.0)
    assert started.started and len(made) == 3
    always = [EOFError("unexpected EOF")] * bench.START_ATTEMPTS
    with pytest.raises(EOFError):
        bench.start_worker(lambda: _FakeWorker(always), retry_s=0.0)
