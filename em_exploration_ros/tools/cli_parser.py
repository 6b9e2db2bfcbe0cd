"""The command-line parser of the package's tools: argparse's, except for how it refuses.

argparse answers a wrong argument with the whole usage text (em-sim's is 11 lines) and then
the error, so the one line that says what is wrong comes last, under the usage. A tool of
this package says what is wrong in one line, where to read on in a second, and exits with
code 2, as run_team.sh does::

    em-sim: error: argument --detection-prob: must be in [0, 1], got 2
    Try 'em-sim --help'.
"""
from __future__ import annotations

import argparse
import sys
from typing import NoReturn


class CliParser(argparse.ArgumentParser):
    """``argparse.ArgumentParser`` whose errors are one line (and the ``--help`` hint) on
    standard error, exit code 2; its subcommands' parsers are of this class too."""

    def refuse(self, message: str) -> int:
        """Print ``<prog>: error: <message>`` and the ``--help`` hint on standard error;
        return 2, the exit code of a refusal (for a tool's own checks after parsing)."""
        sys.stderr.write(f"{self.prog}: error: {message}\nTry '{self.prog} --help'.\n")
        return 2

    def error(self, message: str) -> NoReturn:
        """Refuse as ``refuse`` does and exit with code 2."""
        sys.exit(self.refuse(message))
