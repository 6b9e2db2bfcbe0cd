"""em-bench: benchmarks of the exploration system.

``em-bench planners`` reproduces the paper's planner comparison: seeded trials of several
planners on one or more map settings, each trial one ``TeamRunner`` run in its own worker
process (so a crash costs only that trial). Trials with the same seed see the same world
and noise draws under every planner (paired comparison). Results are kept per trial as
they finish, so a rerun with the same arguments only runs what is missing (failed trials
are retried). Layout of ``--out``::

    trials/<setting>/<planner>/seed_<n>.json   one record per trial (status, params, summary,
                                               code version, numerical kernels)
    results.csv       one row per trial and metrics sample (the curves against distance)
    summary.json      per setting and planner: trials done/failed, final values with 95% CI
    <setting>_<metric>.png, results.md          see bench_plots.py

``em-bench plot --out DIR`` re-makes the plots and results.md from results.csv and
summary.json. Examples::

    em-bench planners --out benchmarks/results --map-size 100 200 --trials 20 --jobs 2
    em-bench planners --out /tmp/b --planners NEAREST CE --map-size 40 --landmarks 4 --trials 2
"""
from __future__ import annotations

import argparse
import csv
import json
import logging
import math
import multiprocessing
import os
import select
import signal
import sys
import time
from collections import defaultdict, deque
from dataclasses import dataclass
from itertools import combinations
from multiprocessing.connection import wait
from pathlib import Path
from typing import Any, Callable, Iterable, Sequence

from em_exploration_ros.core.output_paths import output_path_problem
from em_exploration_ros.core.params import ExplorationParams
from em_exploration_ros.core.params_yaml import ParamsFileError
from em_exploration_ros.core.untrusted_files import (FileTooLarge, NotRegularFile,
                                                    read_regular_file)
from em_exploration_ros.core.evaluation.rendezvous_stats import activity_totals
from em_exploration_ros.core.evaluation.trial_stats import mean_ci, paired_difference
from em_exploration_ros.tools import bench_plots
from em_exploration_ros.tools.bench_trials import (ProgressBar, TrialSpec, code_version,
                                                  describe_error, failed_record, params_record,
                                                  duration_text, run_trial, write_json)
from em_exploration_ros.tools.cli_parser import CliParser
from em_exploration_ros.tools.dataset_bench import (DATASET_HELP, add_dataset_arguments,
                                                   check_dataset_arguments, run_dataset)
from em_exploration_ros.tools.latency_bench import LATENCY_HELP, add_latency_arguments
from em_exploration_ros.tools.sim_cli import (PLANNER_NAMES, PLANNER_TYPE, add_run_arguments,
                                              params_from_args)

_LOG = logging.getLogger("em-bench")

#: The planners of the paper's comparison (the default of --planners).
PAPER_PLANNERS = ("EM_2", "EM_3", "CE", "BSP")
#: Final values reported per planner (keys of the run summary).
FINAL_METRICS = ("explored_ratio", "distance_m", "loc_rmse_m", "landmark_rmse_m", "sim_time_s")
#: Final values compared seed by seed between planners.
PAIRED_METRICS = ("loc_rmse_m", "landmark_rmse_m", "distance_m")
#: The progress line is redrawn this often on a terminal [s].
TTY_REFRESH_S = 1.0
#: The exit code multiprocessing reports for a trial when it cannot learn the real one
#: because the fork server that started the trial died.
FORK_SERVER_LOST_EXIT_CODE = 255
#: How long a worker killed after its fork server died is waited for [s].
ORPHAN_EXIT_WAIT_S = 5.0
#: Tries to start a worker, START_RETRY_S apart [s], when its fork server has just died.
START_ATTEMPTS = 5
START_RETRY_S = 0.1
#: A trial record larger than this is not read [bytes]: the largest of the paper's
#: experiment (200 m, 600 decisions) is about 240 kB.
MAX_RECORD_BYTES = 16 * 1024 * 1024
#: Math libraries in the workers use one thread each: --jobs sets the parallelism.
_SINGLE_THREAD_ENV = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")


def paper_cell_size_m(map_size_m: float) -> float:
    """Default virtual-map cell size [m]: map size / 50, the paper's 2 m (100 m) and 4 m (200 m)."""
    return map_size_m / 50.0


def setting_name(params: ExplorationParams) -> str:
    """Folder and file name of a map setting, e.g. ``100m_cell2m``; a world file's stem
    comes first (``site_120x70m_cell2m``), so two files of one size stay apart."""
    world = params.world
    size = (f"{world.width_m:g}m" if world.width_m == world.height_m
            else f"{world.width_m:g}x{world.height_m:g}m")
    site = f"{Path(world.file).stem}_" if world.file else ""
    return f"{site}{size}_cell{params.map.cell_size_m:g}m"


def trial_specs(args: argparse.Namespace, out_dir: Path, version: str = "unknown"
                ) -> list[TrialSpec]:
    """All trials asked for on the command line, seed-major (ValueError if inconsistent).

    Ordering by seed first interleaves the planners, so partial results stay comparable.
    """
    planners = _planners(args)
    seeds = _seeds(args)
    map_sizes = args.map_size or [None]
    if args.cell_size is not None and len(args.cell_size) != len(map_sizes):
        raise ValueError(f"--cell-size needs one value per map size ({len(map_sizes)}), "
                         f"got {len(args.cell_size)}")
    specs = []
    for index, map_size in enumerate(map_sizes):
        base = params_from_args(_namespace(args, map_size=map_size, cell_size=None, planner=None))
        cell = (args.cell_size[index] if args.cell_size is not None
                else paper_cell_size_m(base.world.width_m))
        run = {} if args.max_distance is None else {"max_distance_m": args.max_distance}
        base = base.replace(map={"cell_size_m": cell}, run=run)
        setting = setting_name(base)
        for seed in seeds:
            for planner in planners:
                params = base.replace(planner={"name": planner}, run={"seed": seed})
                path = out_dir / "trials" / setting / planner / f"seed_{seed}.json"
                specs.append(TrialSpec(setting, planner, seed, params, path, version))
    return specs


def _namespace(args: argparse.Namespace, **changes: Any) -> argparse.Namespace:
    return argparse.Namespace(**{**vars(args), **changes})


def _planners(args: argparse.Namespace) -> list[str]:
    if args.planner is not None and args.planners is not None:
        raise ValueError("give either --planner or --planners")
    if args.planner is not None:
        return [args.planner]
    return list(dict.fromkeys(args.planners or PAPER_PLANNERS))


def _seeds(args: argparse.Namespace) -> list[int]:
    if args.seeds is not None:
        if args.trials is not None or args.seed_start is not None:
            raise ValueError("--seeds replaces --trials and --seed-start")
        return list(dict.fromkeys(args.seeds))
    trials = 20 if args.trials is None else args.trials
    if trials < 1:
        raise ValueError(f"--trials must be at least 1, got {trials}")
    start = 0 if args.seed_start is None else args.seed_start
    return list(range(start, start + trials))


def read_record(path: Path) -> dict[str, Any] | None:
    """A trial record, or None if missing, unreadable, not a regular file (a FIFO would
    block the read), larger than ``MAX_RECORD_BYTES`` or not of a record's shape
    (``record_problem``); a file that is there but unusable is logged, and its trial runs
    again."""
    try:
        record = json.loads(read_regular_file(path, MAX_RECORD_BYTES).decode("utf-8"))
        problem = record_problem(record)
    except FileNotFoundError:
        return None
    except NotRegularFile:
        problem = "not a regular file"
    except FileTooLarge as error:
        problem = f"{error.size} bytes, more than a trial record's {MAX_RECORD_BYTES} at most"
    except (OSError, ValueError) as error:
        problem = f"unreadable ({describe_error(error)})"
    if problem is not None:
        _LOG.warning("%s is not a usable trial record: %s", path, problem)
        return None
    return record


def record_problem(record: Any) -> str | None:
    """Why ``record`` is not what ``trial_record`` or ``failed_record`` writes, or None: it
    needs its setting, planner, seed, parameters and status, and a finished trial its final
    values and history samples (numbers or null), which the summary and results.csv use."""
    if not isinstance(record, dict):
        return "not a JSON object"
    for key, kind in (("setting", str), ("planner", str), ("seed", int), ("params", dict)):
        if not isinstance(record.get(key), kind):
            return f"no {key}"
    if not all(isinstance(record["params"].get(part), dict) for part in ("world", "map", "run")):
        return "its params lack world, map or run"
    if record.get("status") == "failed":
        return None if isinstance(record.get("error"), str) else "a failed trial without its error"
    if record.get("status") != "done":
        return "its status is neither done nor failed"
    summary = record.get("summary")
    if not isinstance(summary, dict) or not _numbers_or_null(summary, FINAL_METRICS):
        return "its summary lacks a final value"
    history = summary.get("history")
    if not isinstance(history, list) or not all(
            isinstance(sample, dict) and _numbers_or_null(sample, bench_plots.CSV_COLUMNS[3:])
            for sample in history):
        return "its history is not a list of samples"
    return None


def _numbers_or_null(data: dict[str, Any], keys: Iterable[str]) -> bool:
    return all(key in data and (data[key] is None or bench_plots.is_number(data[key]))
               for key in keys)


def split_finished(specs: Iterable[TrialSpec]) -> tuple[list[TrialSpec], list[dict[str, Any]]]:
    """Trials still to run, and the records of those finished earlier.

    ValueError if a finished record was made with other parameters (another --out needed),
    or a folder is where a record goes (a trial's old record is removed before it runs).
    """
    to_run, finished = [], []
    for spec in specs:
        record = read_record(spec.path)
        if record is None and spec.path.is_dir():
            raise ValueError(f"{spec.path} is a folder where the record of trial "
                             f"{spec.label} goes; remove it")
        if record is None or record["status"] != "done":
            to_run.append(spec)
            continue
        if record.get("params") != params_record(spec.params):
            raise ValueError(f"{spec.path} holds a trial with other parameters; "
                             "use another --out or remove it")
        finished.append(record)
    return to_run, finished


def trial_context() -> multiprocessing.context.BaseContext:
    """Where trial processes come from: a fork server that imported the trial's modules
    (NumPy, GTSAM, the simulation and the planners: about 0.5 s of CPU) once, so that each
    trial, still a process of its own, starts from a fork of it instead of importing them
    again; set up after the single-thread environment, which the server and every trial
    then share.

    The server imports the modules of this package that this process has imported, by
    name. Each trial then runs the main module again (as multiprocessing does); under
    ``python -m`` that is this module, which this process imported as ``__main__`` only, so
    it is not among them (were it preloaded, every trial would warn that runpy found it
    imported already).
    """
    for name in _SINGLE_THREAD_ENV:
        os.environ.setdefault(name, "1")
    context = multiprocessing.get_context("forkserver")
    context.set_forkserver_preload(sorted(
        name for name in sys.modules if name.startswith("em_exploration_ros.")))
    return context


@dataclass
class _RunningTrial:
    """A trial's worker process and a pidfd of it: the pidfd reaches the process even
    after the fork server, its parent, has died and can no longer report on it."""

    process: multiprocessing.process.BaseProcess
    pidfd: int | None
    spec: TrialSpec
    started_s: float

    def stop_if_orphaned(self) -> None:
        """A worker whose fork server died keeps running, and would write its record
        after this one was written as failed, and run beside the next trials: it is
        killed (and waited for) if it is still alive."""
        if self.pidfd is None or select.select([self.pidfd], [], [], 0.0)[0]:
            return  # gone already (a pidfd is readable once its process has exited)
        _LOG.warning("%s: its worker process (pid %d) outlived its fork server; stopping it",
                     self.spec.label, self.process.pid)
        signal.pidfd_send_signal(self.pidfd, signal.SIGKILL)
        select.select([self.pidfd], [], [], ORPHAN_EXIT_WAIT_S)

    def close(self) -> None:
        if self.pidfd is not None:
            os.close(self.pidfd)


def run_trials(specs: Sequence[TrialSpec], jobs: int, progress: ProgressBar) -> None:
    """Run ``specs`` in at most ``jobs`` worker processes at a time, each trial its own
    process (``trial_context``). A worker that dies without a record gets a failed
    record; one whose fork server died is stopped first (``stop_if_orphaned``), and the
    next trials start from a new fork server."""
    context = trial_context()
    pending = deque(specs)
    progress.queue(specs)
    running: dict[int, _RunningTrial] = {}
    try:
        while pending or running:
            while pending and len(running) < jobs:
                spec = pending.popleft()
                spec.path.unlink(missing_ok=True)
                process = start_worker(
                    lambda spec=spec: context.Process(target=run_trial, args=(spec,),
                                                      name=spec.label))
                running[process.sentinel] = _RunningTrial(process, _pidfd(process.pid), spec,
                                                           time.perf_counter())
                progress.started(spec)
            timeout = TTY_REFRESH_S if progress.interactive else None
            for sentinel in wait(list(running), timeout=timeout):
                trial = running.pop(sentinel)
                trial.process.join()
                if trial.process.exitcode == FORK_SERVER_LOST_EXIT_CODE:
                    trial.stop_if_orphaned()
                trial.close()
                progress.finished(trial.spec, record_after_exit(
                    trial.spec, trial.process.exitcode, time.perf_counter() - trial.started_s))
            progress.refresh()
    finally:
        for trial in running.values():
            trial.process.terminate()
            trial.process.join()
            trial.stop_if_orphaned()
            trial.close()
        progress.close()


def start_worker(make_process: Callable[[], multiprocessing.process.BaseProcess],
                 retry_s: float = START_RETRY_S) -> multiprocessing.process.BaseProcess:
    """A started process from ``make_process()``. A fork server killed a moment before
    still looks alive to multiprocessing, and the start then fails reading the new pid
    (EOFError, or a broken connection); multiprocessing starts a new server at the next
    try, so a new process is tried up to ``START_ATTEMPTS`` times, ``retry_s`` [s] apart."""
    for _ in range(START_ATTEMPTS - 1):
        process = make_process()
        try:
            process.start()
            return process
        except (EOFError, ConnectionError) as error:
            _LOG.warning("%s: could not start its worker (%s: the fork server died?); "
                         "trying again", process.name, type(error).__name__)
            time.sleep(retry_s)
    process = make_process()
    process.start()
    return process


def _pidfd(pid: int) -> int | None:
    """A pidfd of process ``pid``, or None if it has exited and been reaped already."""
    try:
        return os.pidfd_open(pid)
    except ProcessLookupError:
        return None


def record_after_exit(spec: TrialSpec, exitcode: int | None, wall_s: float) -> dict[str, Any]:
    """The record a finished worker wrote, or a failed record if it wrote none."""
    record = read_record(spec.path)
    if record is None:
        error = f"worker process exited with code {exitcode} without a result"
        if exitcode == FORK_SERVER_LOST_EXIT_CODE:
            error += " (or the fork server it came from died)"
        record = failed_record(spec, error, wall_s)
        write_json(spec.path, record)
    return record


def load_records(out_dir: Path) -> list[dict[str, Any]]:
    """Every trial record under ``out_dir/trials``, sorted by setting, planner and seed."""
    records = [read_record(path) for path in (out_dir / "trials").glob("*/*/seed_*.json")]
    return sorted((r for r in records if r is not None),
                  key=lambda r: (r["setting"], r["planner"], r["seed"]))


def write_results_csv(records: Sequence[dict[str, Any]], path: Path) -> int:
    """One row per finished trial and history sample; missing values empty. Returns rows."""
    rows = 0
    with path.open("w", newline="", encoding="utf-8") as stream:
        writer = csv.writer(stream)
        writer.writerow(bench_plots.CSV_COLUMNS)
        for record in records:
            if record["status"] != "done":
                continue
            for sample in record["summary"]["history"]:
                writer.writerow([record["setting"], record["planner"], record["seed"]]
                                + [_csv_value(sample[key]) for key in bench_plots.CSV_COLUMNS[3:]])
                rows += 1
    return rows


def _csv_value(value: float | None) -> str:
    return "" if value is None else repr(float(value))


def summarize(records: Sequence[dict[str, Any]]) -> dict[str, Any]:
    """The summary.json data: per setting, its parameters and per planner the trial counts,
    final values (mean, 95% CI, n), decisions per frontier type, planner failures and
    rendezvous counts summed over the finished trials (``activity``), wall times and
    failures; paired differences between planners over common seeds."""
    by_setting: dict[str, list[dict[str, Any]]] = defaultdict(list)
    for record in records:
        by_setting[record["setting"]].append(record)
    settings = {}
    for setting, group in sorted(by_setting.items(), key=lambda item: _setting_order(item[1])):
        params = group[0]["params"]
        planners: dict[str, list[dict[str, Any]]] = defaultdict(list)
        for record in group:
            planners[record["planner"]].append(record)
        finals = {planner: {r["seed"]: r["summary"] for r in rows if r["status"] == "done"}
                  for planner, rows in planners.items()}
        order = [name for name in PLANNER_NAMES if name in planners]
        settings[setting] = {
            "map_size_m": [params["world"]["width_m"], params["world"]["height_m"]],
            "cell_size_m": params["map"]["cell_size_m"],
            "num_robots": params["world"]["num_robots"],
            "num_landmarks": params["world"]["num_landmarks"],
            "until_explored": params["run"]["until_explored"],
            "max_distance_m": params["run"]["max_distance_m"],
            "max_steps": params["run"]["max_steps"],
            "planners": {name: _planner_summary(planners[name], finals[name],
                                                params["run"]["until_explored"])
                         for name in order},
            "paired_differences": [
                {"a": a, "b": b, "metric": metric,
                 **paired_difference(_metric_by_seed(finals[a], metric),
                                     _metric_by_seed(finals[b], metric)).to_dict()}
                for a, b in combinations(order, 2) for metric in PAIRED_METRICS],
        }
    return {"metrics": list(FINAL_METRICS), "ci": "95% two-sided, Student t (see trial_stats)",
            "settings": settings}


def _setting_order(records: Sequence[dict[str, Any]]) -> tuple[float, float, float]:
    """Settings sort by map width, height and cell size [m]."""
    params = records[0]["params"]
    return (params["world"]["width_m"], params["world"]["height_m"], params["map"]["cell_size_m"])


def _metric_by_seed(finals: dict[int, dict[str, Any]], metric: str) -> dict[int, float]:
    return {seed: math.nan if s[metric] is None else s[metric] for seed, s in finals.items()}


def _planner_summary(records: Sequence[dict[str, Any]], finals: dict[int, dict[str, Any]],
                     until_explored: float) -> dict[str, Any]:
    walls = [r["wall_s"] for r in records if r["status"] == "done"]
    return {
        "trials_done": len(finals),
        "trials_failed": len(records) - len(finals),
        "reached_explored_target": sum(s["explored_ratio"] >= until_explored
                                       for s in finals.values()),
        "final": {metric: mean_ci(list(_metric_by_seed(finals, metric).values())).to_dict()
                  for metric in FINAL_METRICS},
        "activity": activity_totals(finals.values()),
        "wall_s_total": sum(walls),
        "wall_s_mean": sum(walls) / len(walls) if walls else None,
        "code_versions": sorted({r.get("code_version", "unknown") for r in records
                                 if r["status"] == "done"}),
        "math_platforms": sorted({r.get("math_platform", "unknown") for r in records
                                  if r["status"] == "done"}),
        "failures": [{"seed": r["seed"], "error": r["error"]}
                     for r in records if r["status"] != "done"],
    }


def mixed_provenance(summary: dict[str, Any]) -> list[str]:
    """One line per map setting whose finished trials ran more than one code version, or
    on more than one set of numerical kernels (``math_platform``): their values, and the
    paired differences between planners, may then differ for that reason alone."""
    lines = []
    for setting, info in summary["settings"].items():
        for field, what in (("code_versions", "ran {} code versions"),
                            ("math_platforms", "ran on {} sets of numerical kernels")):
            values = bench_plots.setting_values(info, field)
            if len(values) > 1:
                lines.append(f"{setting}: the finished trials {what.format(len(values))} "
                             f"({' | '.join(values)}); their results may differ for that "
                             f"reason alone")
    return lines


def write_outputs(out_dir: Path, last_invocation: dict[str, Any]) -> None:
    """results.csv and summary.json from the trial records, then the plots and results.md;
    a warning for each setting of mixed provenance (``mixed_provenance``)."""
    records = load_records(out_dir)
    rows = write_results_csv(records, out_dir / "results.csv")
    summary = summarize(records)
    write_json(out_dir / "summary.json", {**summary, "last_invocation": last_invocation})
    for line in mixed_provenance(summary):
        _LOG.warning(line)
    made = bench_plots.make_all(out_dir)
    _LOG.info("wrote %s (%d rows), %s, results.md and %d plots", out_dir / "results.csv",
              rows, out_dir / "summary.json", len(made))


def command_planners(args: argparse.Namespace) -> int:
    """``em-bench planners``: run what is missing, then write all outputs."""
    out_dir: Path = args.out
    prepare_out_dir(out_dir)
    if args.dask:
        from em_exploration_ros.tools import bench_dask  # only with --dask: slow import
        bench_dask.parse_address(args.dask)
    specs = trial_specs(args, out_dir, code_version())
    to_run, earlier = split_finished(specs)
    where = f"dask cluster {args.dask}" if args.dask else f"{args.jobs} worker(s)"
    _LOG.info("%d trials: %d finished earlier, %d to run on %s",
              len(specs), len(earlier), len(to_run), where)
    started = time.perf_counter()
    if to_run and args.dask:
        with bench_dask.connect(args.dask) as client:
            progress = ProgressBar(len(to_run), bench_dask.worker_slots(client), sys.stderr,
                                   earlier)
            bench_dask.run_on_cluster(client, to_run, progress)
    elif to_run:
        progress = ProgressBar(len(to_run), args.jobs, sys.stderr, earlier)
        run_trials(to_run, args.jobs, progress)
    wall = time.perf_counter() - started
    _LOG.info("ran %d trials in %s", len(to_run), duration_text(wall))
    write_outputs(out_dir, {"trials": len(specs), "finished_earlier": len(earlier),
                            "ran": len(to_run), "jobs": args.jobs, "dask": args.dask,
                            "wall_s": wall})
    return 0


def command_dataset(args: argparse.Namespace) -> int:
    """``em-bench dataset``: arguments checked, ``--out`` ready, then the replay."""
    checked = check_dataset_arguments(args)
    prepare_out_dir(args.out)
    return run_dataset(args, *checked)


def prepare_out_dir(out_dir: Path) -> None:
    """Create ``--out`` (with its parents) and check that it takes files, before any trial
    runs; ValueError saying why not."""
    if out_dir.exists() and not out_dir.is_dir():
        raise ValueError(f"--out {out_dir} is not a folder")
    try:
        out_dir.mkdir(parents=True, exist_ok=True)
    except OSError as error:
        raise ValueError(f"--out {out_dir}: cannot create the folder ({error.strerror})"
                         ) from None
    problem = output_path_problem(out_dir / "summary.json", "--out")
    if problem is not None:
        raise ValueError(problem)


def command_plot(args: argparse.Namespace,
                 plot: Callable[..., None] = bench_plots.plot_metric) -> int:
    """``em-bench plot``: plots and results.md from saved results (ValueError if they are
    not as em-bench writes them); ``plot`` draws each PNG (``bench_plots.make_all``)."""
    try:
        made = bench_plots.make_all(args.out, plot)
    except ValueError as error:  # bench_plots names what in which file is not as it writes
        raise ValueError(f"cannot make the plots from {args.out}: its summary.json or "
                         f"results.csv is not as em-bench writes it ({error})") from None
    except OSError as error:
        raise ValueError(f"cannot make the plots from {args.out}: {describe_error(error)}"
                         ) from None
    _LOG.info("wrote %s and %d plots", args.out / "results.md", len(made))
    return 0


def build_parser() -> argparse.ArgumentParser:
    """The em-bench argument parser, one subcommand per benchmark."""
    parser = CliParser(prog="em-bench", description="Benchmarks of the "
                       "multi-robot exploration system.")
    commands = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    planners = commands.add_parser(
        "planners", help="compare planners over seeded trials (the paper's comparison)",
        description="Seeded trials of several planners on one or more map settings, in "
        "parallel worker processes, resumable; writes CSV, JSON summary, plots, results.md.")
    add_run_arguments(planners, sweep_map_sizes=True)
    planners.add_argument("--planners", nargs="+", type=PLANNER_TYPE, choices=PLANNER_NAMES,
                          help=f"planners to compare (default {' '.join(PAPER_PLANNERS)})")
    planners.add_argument("--trials", type=int, help="trials (seeds) per planner (default 20)")
    planners.add_argument("--seed-start", type=int, help="first seed (default 0)")
    planners.add_argument("--seeds", type=int, nargs="+", help="explicit seeds")
    planners.add_argument("--max-distance", type=float, metavar="M",
                          help="stop a trial when the team has travelled this far [m]")
    planners.add_argument("--jobs", type=int, default=os.cpu_count() or 1,
                          help="parallel worker processes (default: number of CPUs)")
    planners.add_argument("--dask", metavar="ADDRESS",
                          help="run the trials on a dask.distributed cluster instead of "
                          "--jobs local worker processes: local:N (a local cluster of N "
                          "worker processes) or a scheduler address, e.g. tcp://host:8786")
    planners.add_argument("--out", type=Path, required=True, help="output folder")
    planners.set_defaults(handler=command_planners,
                          interrupted="interrupted; finished trials are kept, rerun to resume")
    planners.epilog = ("--map-size and --cell-size take one or more values (one cell size "
                       "per map size; default map size / 50: 2 m for 100 m, 4 m for 200 m).")

    plot = commands.add_parser("plot", help="re-make plots and results.md from saved results")
    plot.add_argument("--out", type=Path, required=True,
                      help="folder holding results.csv and summary.json")
    plot.set_defaults(handler=command_plot)
    add_latency_arguments(commands.add_parser("latency", help=LATENCY_HELP))
    dataset = commands.add_parser("dataset", help=DATASET_HELP)
    add_dataset_arguments(dataset)
    dataset.set_defaults(handler=command_dataset)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of em-bench; returns the process exit code."""
    parser = build_parser()
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(name)s: %(message)s")
    if getattr(args, "jobs", 1) < 1:
        parser.error("--jobs must be at least 1")
    try:
        return args.handler(args)
    except (ParamsFileError, ValueError, FileNotFoundError) as error:
        return parser.refuse(str(error))
    except KeyboardInterrupt:
        _LOG.warning("%s", getattr(args, "interrupted", "interrupted"))
        return 130


if __name__ == "__main__":
    sys.exit(main())
