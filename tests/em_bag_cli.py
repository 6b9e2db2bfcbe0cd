"""Running the em-bag command inside the test process (shared by the bag tests)."""
from __future__ import annotations

import pytest

from em_exploration_ros.tools import bag


def run_em_bag(capsys: pytest.CaptureFixture[str], *args: str) -> tuple[int, str, str]:
    """(exit code, stdout, stderr) of em-bag run in this process."""
    try:
        bag.main(list(args))
        code = 0
    except SystemExit as stopped:
        code = stopped.code
    captured = capsys.readouterr()
    return code, captured.out, captured.err
