"""Note in a run's summary whether its recording is complete (run_team.sh --record).

    python -m em_exploration_ros.tools.summary_recording SUMMARY BAG [PROBLEM]

adds ``"recording": {"path": BAG, "complete": PROBLEM is empty, "problem": PROBLEM or null}``
to the summary JSON, replacing the file whole (``write_replacing``). PROBLEM is what ended
the recording early (em-record's exit code and its last line), empty if it ran to the end.
Exit code 0, or 1 with one line on stderr if the summary cannot be read or written.
"""
from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Any

from em_exploration_ros.core.output_paths import write_replacing
from em_exploration_ros.core.untrusted_files import read_regular_file

#: Largest summary read [bytes]: a 200 m mission's is about 1 MB.
MAX_SUMMARY_BYTES = 64 * 1024 * 1024


def recording_entry(bag: str, problem: str) -> dict[str, Any]:
    """The summary's ``recording`` entry: where the bag is and whether it holds the whole run."""
    return {"path": bag, "complete": not problem, "problem": problem or None}


def main(argv: list[str] | None = None) -> int:
    """Entry point; returns the exit code."""
    args = sys.argv[1:] if argv is None else argv
    if len(args) not in (2, 3):
        sys.stderr.write("usage: summary_recording SUMMARY BAG [PROBLEM]\n")
        return 1
    path, bag, problem = Path(args[0]), args[1], args[2] if len(args) == 3 else ""
    try:
        summary = json.loads(read_regular_file(path, MAX_SUMMARY_BYTES).decode("utf-8"))
        if not isinstance(summary, dict):
            raise ValueError("not a JSON object")
        summary["recording"] = recording_entry(bag, problem)
        text = json.dumps(summary, indent=2) + "\n"
        write_replacing(path, lambda partial: partial.write_text(text, encoding="utf-8"))
    except (OSError, ValueError) as error:
        sys.stderr.write(f"summary_recording: {path}: {error}\n")
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
