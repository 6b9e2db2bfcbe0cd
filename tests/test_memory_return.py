"""A node process hands the memory it freed back to the system (nodes/memory_return.py)."""
from __future__ import annotations

import time

import pytest

from em_exploration_ros.nodes.lean_executor import LeanExecutor
from em_exploration_ros.nodes.memory_return import _malloc_trim, return_freed_memory

from test_lean_executor import node_on


def rss_mb() -> float:
    with open("/proc/self/status", encoding="ascii") as status:
        return next(int(line.split()[1]) for line in status if line.startswith("VmRSS:")) / 1024


@pytest.mark.skipif(_malloc_trim() is None, reason="the C library has no malloc_trim (not glibc)")
def test_memory_freed_below_a_live_allocation_goes_back_to_the_system():
    """100 MB of 2 kB buffers, one in 50 kept: glibc keeps the freed memory below the kept
    ones until the node's timer trims it."""
    with node_on(LeanExecutor) as (node, executor):
        buffers = [bytearray(2000) for _ in range(50_000)]
        kept = buffers[::50]
        del buffers
        held_mb = rss_mb()
        timer = return_freed_memory(node, period_s=0.05)
        assert timer is not None
        deadline = time.monotonic() + 10.0
        while rss_mb() > held_mb - 50.0 and time.monotonic() < deadline:
            executor.spin_once(timeout_sec=0.1)
        assert rss_mb() <= held_mb - 50.0, f"{held_mb:.0f} MB held, {rss_mb():.0f} MB now"
        assert len(kept) == 1000
