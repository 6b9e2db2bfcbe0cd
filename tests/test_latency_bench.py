"""em-bench latency: runs on small graphs, reports the fast EM step equal to its oracle, the
approximate U_M's error and a per-candidate line fit."""
import signal
import subprocess
import sys

from process_tree import interruptible


def test_latency_table_is_printed_with_oracle_agreement_and_fits():
    result = subprocess.run(
        [sys.executable, "-m", "em_exploration_ros.tools.bench", "latency", "--sizes", "60",
         "90", "--repeats", "1", "--planners", "EM_3", "CE", "--approximate", "1.0"],
        capture_output=True, text=True, timeout=180)
    assert result.returncode == 0, result.stderr
    lines = result.stdout.strip().splitlines()
    assert lines[0].startswith("machine:") and "EM_3" in lines[2] and "CE" in lines[2]
    for line, size in ((lines[3], 60), (lines[4], 90)):
        row = line.split()
        poses, variables, candidates = int(row[0]), int(row[1]), int(row[2])
        assert size - 10 <= poses <= size and variables > poses and candidates >= 10
        em_cpu, em_per_candidate = float(row[5]), float(row[6])
        assert abs(em_per_candidate - em_cpu / candidates) <= 0.01 + 1e-3 * em_cpu
        agreement, approximate_error = float(row[-4]), float(row[-3])
        assert agreement < 1e-6  # fast low-rank path equals the re-solve oracle
        # Tolerance 1: every history pose keeps its current contribution, U_M differs.
        assert approximate_error > 0.0 and row[-2] in ("yes", "no")
    assert "authors: a = 0.057 s, b = 2.7e-4 s" in lines[5]
    assert lines[6].split()[0] == "EM_3:" and "of the authors' slope" in lines[6]
    assert lines[7].split()[0] == "CE:"


def test_arguments_that_give_no_measurement_are_refused_before_anything_runs():
    for arguments, message in ((["--sizes", "250", "0"], "--sizes: every graph needs at least "
                                "one pose per robot (3), got 0"),
                               (["--repeats", "0"], "--repeats must be at least 1, got 0"),
                               (["--sizes", "30", "30"], "--sizes: 30 given more than once"),
                               (["--planners", "NEAREST", "CE", "NEAREST"],
                                "--planners: NEAREST given more than once"),
                               (["--seed", "-1"], "--seed must not be negative, got -1"),
                               (["--approximate", "nan"], "history_change_tolerance must be "
                                "finite")):
        result = subprocess.run(
            [sys.executable, "-m", "em_exploration_ros.tools.bench", "latency", *arguments],
            capture_output=True, text=True, timeout=60)
        assert result.returncode == 2 and message in result.stderr, result.stderr
        assert result.stdout == ""  # refused before the table's header


def test_ctrl_c_says_interrupted_without_a_traceback():
    """An interrupted latency run ends with exit code 130 and one line; it has no trials,
    so it does not speak of resuming them as `em-bench planners` does."""
    process = subprocess.Popen(
        [sys.executable, "-m", "em_exploration_ros.tools.bench", "latency", "--planners",
         "EM_3", "--sizes", "250", "--repeats", "1000"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, preexec_fn=interruptible)
    try:
        assert "poses" in "".join(process.stdout.readline() for _ in range(3))
        process.send_signal(signal.SIGINT)
        _, stderr = process.communicate(timeout=60)
    finally:
        process.kill()
    assert process.returncode == 130, stderr
    assert stderr.strip().splitlines()[-1] == "em-bench: interrupted", stderr
    assert "Traceback" not in stderr
