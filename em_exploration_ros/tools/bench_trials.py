"""One benchmark trial, as both of em-bench's runners (the local worker pool in
``bench.py``, the dask cluster in ``bench_dask.py``) see it: what it is (``TrialSpec``), the
code version it ran, how it runs and what it records (done or failed, with its error), where
the record goes, and the progress line over many trials."""
from __future__ import annotations

import dataclasses
import json
import math
import subprocess
import sys
import time
import traceback
from collections import defaultdict
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Sequence, TextIO

from em_exploration_ros.core.output_paths import write_replacing
from em_exploration_ros.core.params import ExplorationParams
from em_exploration_ros.core.sessions.team_runner import TeamRunner
from em_exploration_ros.tools import math_platform

#: A failed trial's error is summarized in at most this many characters (the record also
#: keeps the traceback).
ERROR_CHARS = 200

@dataclass(frozen=True)
class TrialSpec:
    """One trial: a planner on a map setting with one seed, and where its record goes."""

    setting: str
    planner: str
    seed: int
    params: ExplorationParams
    path: Path
    code_version: str = "unknown"

    @property
    def label(self) -> str:
        """Short human-readable name."""
        return f"{self.setting}/{self.planner}/seed {self.seed}"

def code_version() -> str:
    """``git describe --always --dirty`` of the checkout this package runs from, else
    ``unknown``. Stored with every trial, so results of different code stay visible."""
    try:
        result = subprocess.run(["git", "describe", "--always", "--dirty"],
                                cwd=Path(__file__).resolve().parent, capture_output=True,
                                text=True, timeout=30, check=True)
    except (OSError, subprocess.SubprocessError):
        return "unknown"
    return result.stdout.strip() or "unknown"

def params_record(params: ExplorationParams) -> dict[str, Any]:
    """Parameters as JSON data (tuples become lists), for storing and comparing."""
    return json.loads(json.dumps(dataclasses.asdict(params)))

def write_json(path: Path, data: dict[str, Any]) -> None:
    """Write JSON whole or not at all (``write_replacing``), its folder made first."""
    path.parent.mkdir(parents=True, exist_ok=True)
    text = json.dumps(data, indent=1) + "\n"
    write_replacing(path, lambda temporary: temporary.write_text(text, encoding="utf-8"))


def _base_record(spec: TrialSpec) -> dict[str, Any]:
    return {"setting": spec.setting, "planner": spec.planner, "seed": spec.seed,
            "code_version": spec.code_version, "params": params_record(spec.params)}


def trial_record(spec: TrialSpec) -> dict[str, Any]:
    """Run one trial; its record (status done or failed, wall time, and the numerical
    kernels of the process that ran it: ``math_platform.describe``)."""
    started = time.perf_counter()
    record = _base_record(spec)
    record["math_platform"] = math_platform.describe()
    try:
        summary = TeamRunner(spec.params).run()
        record.update(status="done", summary=summary.to_dict())
    except Exception as error:  # noqa: BLE001 - any failure of a trial is recorded, not raised
        record.update(status="failed", error=describe_error(error),
                      traceback=traceback.format_exc())
    record["wall_s"] = time.perf_counter() - started
    return record


def run_trial(spec: TrialSpec) -> None:
    """Worker process entry: run one trial and write its record. Ctrl-C reaches every
    process of the terminal's process group; a worker then ends quietly with exit code 130
    and no record, as em-bench itself reports the interruption (the trial runs again on
    resuming)."""
    try:
        write_json(spec.path, trial_record(spec))
    except KeyboardInterrupt:
        sys.exit(130)


def failed_record(spec: TrialSpec, error: str, wall_s: float) -> dict[str, Any]:
    """The record of a trial that ended without a record of its own."""
    record = _base_record(spec)
    record.update(status="failed", wall_s=wall_s, error=error)
    return record


def describe_error(error: BaseException) -> str:
    """One line naming an exception: its type and message, whitespace collapsed, shortened."""
    text = f"{type(error).__name__}: {' '.join(str(error).split())}"
    return text if len(text) <= ERROR_CHARS else text[:ERROR_CHARS - 3] + "..."

def duration_text(seconds: float | None) -> str:
    """``h:mm:ss`` of a duration [s], or ``--:--:--`` when it is unknown."""
    if seconds is None or not math.isfinite(seconds):
        return "--:--:--"
    seconds = int(round(seconds))
    return f"{seconds // 3600}:{seconds // 60 % 60:02d}:{seconds % 60:02d}"


class ProgressBar:
    """Trial progress and estimated time left, on a text stream.

    On a terminal one line is redrawn in place (``\\r``); otherwise one line is written per
    finished trial. The time left assumes a pending trial takes as long as the mean of
    the finished trials of its setting and planner (else of all finished trials).
    """

    WIDTH = 24

    def __init__(self, total: int, jobs: int, stream: TextIO,
                 earlier: Sequence[dict[str, Any]] = (),
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.total = total
        self.jobs = max(jobs, 1)
        self.stream = stream
        self.interactive = stream.isatty()
        self.clock = clock
        self.started_at = clock()
        self.done = 0
        self.failed = 0
        self.running: dict[str, tuple[TrialSpec, float]] = {}
        self.pending: list[TrialSpec] = []
        self._walls: dict[tuple[str, str], list[float]] = defaultdict(list)
        for record in earlier:
            self._walls[record["setting"], record["planner"]].append(record["wall_s"])

    def queue(self, specs: Sequence[TrialSpec]) -> None:
        """Trials waiting for a worker."""
        self.pending = list(specs)

    def started(self, spec: TrialSpec) -> None:
        """A worker took ``spec``."""
        self.pending.remove(spec)
        self.running[spec.label] = (spec, self.clock())

    def finished(self, spec: TrialSpec, record: dict[str, Any]) -> None:
        """A trial ended with ``record``."""
        self.running.pop(spec.label, None)
        self._walls[spec.setting, spec.planner].append(record["wall_s"])
        if record["status"] == "done":
            self.done += 1
            result = record["summary"]
            outcome = (f"done in {record['wall_s']:.1f} s (explored "
                       f"{result['explored_ratio']:.3f}, {result['distance_m']:.0f} m)")
        else:
            self.failed += 1
            outcome = f"FAILED after {record['wall_s']:.1f} s: {record['error']}"
        if self.interactive:
            self.stream.write("\r\033[K")
        count = self.done + self.failed
        self.stream.write(f"[{count}/{self.total}] {spec.label}: {outcome} | "
                          f"{self._times()}\n")
        self.refresh()

    def refresh(self) -> None:
        """Redraw the status line (terminal only)."""
        if not self.interactive:
            return
        count = self.done + self.failed
        filled = self.WIDTH * count // max(self.total, 1)
        bar = "#" * filled + "." * (self.WIDTH - filled)
        self.stream.write(f"\r\033[K[{bar}] {count}/{self.total} trials, {self.failed} failed, "
                          f"{len(self.running)} running | {self._times()}")
        self.stream.flush()

    def close(self) -> None:
        """End the status line."""
        if self.interactive:
            self.stream.write("\n")
        self.stream.flush()

    def eta_s(self) -> float | None:
        """Estimated wall time left [s], None while nothing has finished."""
        everything = [wall for walls in self._walls.values() for wall in walls]
        if not everything:
            return None
        overall = sum(everything) / len(everything)

        def expected(spec: TrialSpec) -> float:
            walls = self._walls.get((spec.setting, spec.planner))
            return sum(walls) / len(walls) if walls else overall

        now = self.clock()
        work = sum(expected(spec) for spec in self.pending)
        work += sum(max(expected(spec) - (now - since), 0.0)
                    for spec, since in self.running.values())
        return work / self.jobs

    def _times(self) -> str:
        return (f"elapsed {duration_text(self.clock() - self.started_at)}, "
                f"left ~{duration_text(self.eta_s())}")
