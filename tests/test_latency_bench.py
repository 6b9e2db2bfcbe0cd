"""em-bench latency: runs on a small graph and reports the fast EM step equal to its oracle."""
import subprocess
import sys


def test_latency_table_is_printed_with_oracle_agreement():
    result = subprocess.run(
        [sys.executable, "-m", "em_exploration_ros.tools.bench", "latency", "--sizes", "90",
         "--repeats", "1", "--planners", "EM_3", "CE"], capture_output=True, text=True,
        timeout=120)
    assert result.returncode == 0, result.stderr
    lines = result.stdout.strip().splitlines()
    assert lines[0].startswith("machine:") and "EM_3" in lines[2] and "CE" in lines[2]
    row = lines[3].split()
    poses, candidates, agreement = int(row[0]), int(row[1]), float(row[-1])
    assert 80 <= poses <= 90 and candidates >= 10
    assert agreement < 1e-6  # fast low-rank path equals the re-solve oracle
