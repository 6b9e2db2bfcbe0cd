"""Giving back to the system the memory a node process has freed (glibc's ``malloc_trim``).

After a flood, the memory the middleware and Python freed stayed with the process: glibc
returns a heap's free memory to the system only from its top, and one live allocation above
the freed ones kept it all (the evaluator's heap stayed at 100 MB after em-fuzz flooded
every topic for 60 s, against 32 MB in a clean run). ``malloc_trim(0)`` hands every whole
free page back, wherever it lies. Each node process calls it every ``TRIM_PERIOD_S`` of
wall time: 0.01-0.03 ms when there is little to return, 10-20 ms after a flood freed 100 MB.
A C library without ``malloc_trim`` (not glibc) keeps its own policy: nothing is called.
"""
from __future__ import annotations

import ctypes
import ctypes.util
from typing import Callable

from rclpy.clock import Clock, ClockType
from rclpy.node import Node
from rclpy.timer import Timer

#: Wall seconds between two calls of ``malloc_trim`` in a node process. A short team run
#: ends a few wall seconds after a flood: with 10 s the evaluator sometimes ended before a
#: trim came and kept up to 40 MB that it had freed (tests/test_flood_memory.py).
TRIM_PERIOD_S = 1.0


def _malloc_trim() -> Callable[[int], int] | None:
    """glibc's ``malloc_trim``, or None where the C library has none."""
    name = ctypes.util.find_library("c")
    try:
        library = ctypes.CDLL(name)
    except OSError:
        return None
    trim = getattr(library, "malloc_trim", None)
    if trim is not None:
        trim.argtypes, trim.restype = [ctypes.c_size_t], ctypes.c_int
    return trim


def return_freed_memory(node: Node, period_s: float = TRIM_PERIOD_S) -> Timer | None:
    """Call ``malloc_trim(0)`` every ``period_s`` wall seconds on ``node``'s executor (a
    steady-clock timer: in lockstep the simulated clock stands still); None (no timer)
    without glibc."""
    trim = _malloc_trim()
    if trim is None:
        return None
    return node.create_timer(period_s, lambda: trim(0),
                             clock=Clock(clock_type=ClockType.STEADY_TIME))
