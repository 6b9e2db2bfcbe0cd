"""Helpers for tests that start ROS 2 node processes: bounded in time, always cleaned up.

Every process is started in its own session (so its own process group) with the test run's
environment (ROS_DOMAIN_ID and ROS_AUTOMATIC_DISCOVERY_RANGE set by tests/conftest.py),
its output in a log file. ``stop()`` sends SIGINT to the group, then SIGTERM, then SIGKILL,
each after a grace period, so no process outlives its test::

    with NodeProcess.start_module("em_exploration_ros.nodes.world_node",
                                  ros_args(params={"world.num_robots": 2}),
                                  log_path=tmp_path / "world.log") as world:
        wait_until(lambda: "stepping" in world.output(), 20.0, "world start")

``ProcessSet`` stops several processes together (a pytest fixture can yield one).
"""
from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import time
from contextlib import contextmanager
from pathlib import Path
from typing import Any, Callable, Iterable, Iterator, Mapping, Sequence

import pytest

from process_tree import interruptible

REPO_ROOT = Path(__file__).resolve().parents[1]


def ros_value(value: Any) -> str:
    """A Python value as a ``-p name:=value`` literal (floats keep a decimal point)."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, float):
        return repr(value)
    if isinstance(value, (list, tuple)):
        return "[" + ", ".join(ros_value(v) for v in value) + "]"
    return str(value)


def loaded_modules(*imported: str) -> set[str]:
    """The names in ``sys.modules`` of a fresh Python process after it imported ``imported``
    (what a node process loads, without starting it)."""
    script = ("import importlib, sys\n"
              f"for name in {list(imported)!r}:\n"
              "    importlib.import_module(name)\n"
              "print('\\n'.join(sys.modules))\n")
    result = subprocess.run([sys.executable, "-c", script], cwd=REPO_ROOT, capture_output=True,
                            text=True, timeout=120)
    assert result.returncode == 0, result.stderr
    return set(result.stdout.split())


def ros_args(params: Mapping[str, Any] | None = None, namespace: str | None = None,
             params_file: str | Path | None = None, extra: Sequence[str] = ()) -> list[str]:
    """``--ros-args`` arguments: optional namespace remap, parameter file, then ``-p``s."""
    args = ["--ros-args"]
    if namespace:
        args += ["-r", f"__ns:={namespace}"]
    if params_file is not None:
        args += ["--params-file", str(params_file)]
    for name, value in (params or {}).items():
        args += ["-p", f"{name}:={ros_value(value)}"]
    return args + list(extra)


@contextmanager
def graph_reader(domain: str | None = None) -> Iterator[Any]:
    """An rclpy node (its own context) in this test run's domain (or in ``domain``), to read
    the ROS graph."""
    import rclpy
    from rclpy.node import Node
    context = rclpy.Context()
    rclpy.init(context=context, domain_id=None if domain is None else int(domain))
    node = Node("graph_inspector", context=context)
    try:
        yield node
    finally:
        node.destroy_node()
        rclpy.try_shutdown(context=context)


def wait_until(condition: Callable[[], bool], timeout_s: float, what: str,
               poll_s: float = 0.05, while_waiting: Callable[[], None] | None = None) -> None:
    """Poll ``condition`` until it holds; raise ``TimeoutError`` naming ``what`` after
    ``timeout_s`` wall seconds. ``while_waiting`` runs between polls (e.g. spin a node)."""
    deadline = time.monotonic() + timeout_s
    while not condition():
        if time.monotonic() > deadline:
            raise TimeoutError(f"timed out after {timeout_s:g} s waiting for {what}")
        if while_waiting is not None:
            while_waiting()
        else:
            time.sleep(poll_s)


class NodeProcess:
    """One child process in its own process group, output to ``log_path``."""

    def __init__(self, command: Sequence[str], log_path: Path,
                 env: Mapping[str, str] | None = None, cwd: Path = REPO_ROOT) -> None:
        self.command = list(command)
        self.log_path = Path(log_path)
        self.log_path.parent.mkdir(parents=True, exist_ok=True)
        environment = dict(os.environ)
        environment.setdefault("PYTHONUNBUFFERED", "1")
        environment.setdefault("RCUTILS_LOGGING_BUFFERED_STREAM", "1")
        environment.update(env or {})
        with open(self.log_path, "wb") as log:
            self.process = subprocess.Popen(self.command, stdout=log, stderr=subprocess.STDOUT,
                                            stdin=subprocess.DEVNULL, env=environment,
                                            cwd=cwd, start_new_session=True,
                                            preexec_fn=interruptible)

    @classmethod
    def start_module(cls, module: str, args: Sequence[str] = (), log_path: Path | None = None,
                     env: Mapping[str, str] | None = None) -> "NodeProcess":
        """``python -m module args`` with this interpreter; log in ``log_path``."""
        log = log_path or Path(REPO_ROOT / "build" / f"{module.rsplit('.', 1)[-1]}.log")
        return cls([sys.executable, "-m", module, *args], log, env)

    @classmethod
    def run_script(cls, source: str, log_path: Path, timeout_s: float) -> tuple[int, str]:
        """Run Python ``source`` (``python -c``, the repository importable) to its end;
        its exit code and output. Stopped (and the test failed) after ``timeout_s``."""
        process = cls([sys.executable, "-c", source], log_path,
                      env={"PYTHONPATH": str(REPO_ROOT)})
        with process:
            code = process.wait(timeout_s)
        return code, process.output()

    @property
    def pid(self) -> int:
        """Process id, which is also the id of its process group."""
        return self.process.pid

    def running(self) -> bool:
        """True while the process has not exited."""
        return self.process.poll() is None

    def output(self) -> str:
        """Everything the process has written so far."""
        return self.log_path.read_text(encoding="utf-8", errors="replace")

    def wait_for_output(self, text: str, timeout_s: float,
                        while_waiting: Callable[[], None] | None = None) -> None:
        """Wait until ``text`` appears in the output; fail early if the process exits.
        ``while_waiting`` runs between polls (``wait_until``)."""
        def seen() -> bool:
            if text in self.output():
                return True
            if not self.running():
                raise RuntimeError(f"{self.command[:3]} exited with {self.process.returncode} "
                                   f"before printing {text!r}:\n{self.output()[-3000:]}")
            return False
        wait_until(seen, timeout_s, f"{text!r} in {self.log_path.name}",
                   while_waiting=while_waiting)

    def wait(self, timeout_s: float) -> int:
        """Wait for the process to exit by itself; its exit code (TimeoutError if not)."""
        try:
            return self.process.wait(timeout=timeout_s)
        except subprocess.TimeoutExpired:
            raise TimeoutError(f"{self.command[:3]} still running after {timeout_s:g} s") from None

    def signal_group(self, signum: int) -> None:
        """Send ``signum`` to the process group (ignored if it is gone)."""
        try:
            os.killpg(self.process.pid, signum)
        except ProcessLookupError:
            pass

    def stop(self, grace_s: float = 5.0) -> int | None:
        """SIGINT the group; after ``grace_s`` SIGTERM, then SIGKILL. Returns the exit code
        of the process (None only if even SIGKILL did not end it in time)."""
        for signum, wait_s in ((signal.SIGINT, grace_s), (signal.SIGTERM, 2.0),
                               (signal.SIGKILL, 2.0)):
            if self.running():
                self.signal_group(signum)
            try:
                self.process.wait(timeout=wait_s)
                break
            except subprocess.TimeoutExpired:
                continue
        # The leader may be gone while other members of its group live on.
        self.signal_group(signal.SIGKILL)
        return self.process.poll()

    def __enter__(self) -> "NodeProcess":
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()


class ProcessSet:
    """Several NodeProcess objects stopped together (in reverse start order)."""

    def __init__(self) -> None:
        self.processes: list[NodeProcess] = []

    def add(self, process: NodeProcess) -> NodeProcess:
        """Track an already started process; returns it."""
        self.processes.append(process)
        return process

    def start_module(self, module: str, args: Sequence[str] = (), log_path: Path | None = None,
                     env: Mapping[str, str] | None = None) -> NodeProcess:
        """Start and track ``python -m module args`` (see NodeProcess.start_module)."""
        return self.add(NodeProcess.start_module(module, args, log_path, env))

    def stop_all(self, grace_s: float = 5.0) -> None:
        """SIGINT every group at once, then stop each as NodeProcess.stop does."""
        for process in reversed(self.processes):
            if process.running():
                process.signal_group(signal.SIGINT)
        for process in reversed(self.processes):
            process.stop(grace_s)

    def __enter__(self) -> "ProcessSet":
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop_all()


def processes_in_domain(pattern: str, domain_id: str | int,
                        exclude: Iterable[int] = ()) -> list[int]:
    """PIDs whose command line matches ``pattern`` (``pgrep -f``) and whose environment has
    ``ROS_DOMAIN_ID=domain_id``: this test run's processes, not other runs' on the machine."""
    found = subprocess.run(["pgrep", "-f", pattern], capture_output=True, text=True).stdout
    excluded = set(exclude) | {os.getpid()}
    marker = f"ROS_DOMAIN_ID={domain_id}".encode()
    pids = []
    for pid in (int(p) for p in found.split()):
        if pid in excluded:
            continue
        try:
            environment = Path(f"/proc/{pid}/environ").read_bytes().split(b"\0")
        except OSError:
            continue
        if marker in environment:
            pids.append(pid)
    return pids


#: launch_scripts/run_team.sh, the README's main command.
RUN_TEAM = REPO_ROOT / "launch_scripts" / "run_team.sh"
#: A run's processes, as their command lines name them.
RUN_PROCESS_PATTERN = r"em_exploration_ros\.(nodes|tools)\."
#: The domain run_team.sh announces in its first line ("..., ROS_DOMAIN_ID=12; logs in ...").
CHOSEN_DOMAIN = re.compile(r"ROS_DOMAIN_ID=(\d+);")


def start_team_run(tmp_path: Path, *args: str,
                   beside: ProcessSet | None = None) -> tuple[NodeProcess, str]:
    """run_team.sh with ``args`` in this test run's domain; waits until the world, the
    evaluator and every robot (``--robots``, default 3) run, which also shows the leftover
    check can see them, or until the run has ended. ``beside``: a run that goes on beside
    another one of this test, in a free domain that run_team.sh chooses and holds instead
    (read from its first lines), tracked in ``beside`` from its start, so that the test can
    stop it from another thread (``ProcessSet.stop_all``)."""
    robots = int(args[args.index("--robots") + 1]) if "--robots" in args else 3
    if beside is not None:
        run = beside.add(NodeProcess(["bash", str(RUN_TEAM), *args],
                                     tmp_path / "run_team.out"))
        try:
            wait_until(lambda: CHOSEN_DOMAIN.search(run.output()) or not run.running(), 60.0,
                       "run_team.sh's domain")
        except TimeoutError:
            run.stop()
            raise
        chosen = CHOSEN_DOMAIN.search(run.output())
        domain = chosen.group(1) if chosen else "none"
    else:
        domain = os.environ["ROS_DOMAIN_ID"]
        run = NodeProcess(["bash", str(RUN_TEAM), *args, "--domain-id", domain],
                          tmp_path / "run_team.out")
    try:
        wait_until(lambda: len(processes_in_domain(RUN_PROCESS_PATTERN, domain)) >= 2 + robots
                   or not run.running(), 60.0, f"the run's {2 + robots} processes")
    except TimeoutError:
        run.stop()
        raise
    return run, domain


def robot_pid(domain: str, robot_id: int) -> int:
    """The PID of robot ``robot_id``'s process in this test run's domain (exactly one)."""
    pids = processes_in_domain(rf"robot_node.*robot_id:={robot_id}( |$)", domain)
    assert len(pids) == 1, f"robot {robot_id}: processes {pids}"
    return pids[0]


def wait_for_liveliness(log: Path, robot_id: int, timeout_s: float,
                        while_waiting: Callable[[], None] | None = None) -> None:
    """Until ``log`` (the world's or the evaluator's, under a run's ``logs/``) says robot
    ``robot_id``'s liveliness was asserted. Before that, a killed or stopped robot is noticed
    only after ``robot_timeout_s`` (30 s), not ``liveliness_grace_s`` (4 s): a test that
    stops a robot early must wait for this (a 20x team is 20 simulated seconds in before
    discovery has always matched). ``while_waiting`` as in ``wait_until``."""
    wait_until(lambda: log.exists() and f"robot {robot_id}: liveliness asserted"
               in log.read_text(), timeout_s, f"robot {robot_id}'s liveliness in {log.name}",
               while_waiting=while_waiting)


def finish_team_run(run: NodeProcess, timeout_s: float,
                    meanwhile: Callable[[], None] | None = None) -> int:
    """The exit code of a run_team.sh run (``start_team_run``), after ``meanwhile()`` (e.g.
    killing a robot); fails the test with the run's last output if it does not end within
    ``timeout_s``. The run is stopped whatever happens."""
    with run:
        try:
            if meanwhile is not None:
                meanwhile()
            return run.wait(timeout_s)
        except TimeoutError:
            pytest.fail(f"run_team.sh did not finish in {timeout_s} s:\n"
                        f"{run.output()[-3000:]}")
