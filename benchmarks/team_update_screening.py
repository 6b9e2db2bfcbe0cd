"""Where a flooded reader's time goes: em-fuzz's team updates read whole or by their head.

Builds em-fuzz's pools of TeamUpdate messages (``--pools`` seeds, ``fuzz.POOL_SIZE`` each,
with the run id ``RUN_ID``) and times, per message, what a robot did with each before
``input_guard.screened_team_updates`` (rclpy's ``deserialize_message`` and
``content_problem``) and what it does now first (``update_screening.screen_team_update``).
Prints the sizes, the times (mean, and of the largest messages) and how many messages the head
alone drops for a receiver of robot 1's topic that expects sequence number ``EXPECTED``.

Usage: ``.venv/bin/python benchmarks/team_update_screening.py [--pools 50]``
"""
from __future__ import annotations

import argparse
import random
import statistics
import time

from em_exploration_msgs.msg import TeamUpdate
from rclpy._rclpy_pybind11 import RMWError
from rclpy.serialization import deserialize_message

from em_exploration_ros.core.records.update_screening import only_sender, screen_team_update
from em_exploration_ros.nodes.input_guard import content_problem
from em_exploration_ros.tools.fuzz import POOL_SIZE, ExtremeMessages, Target

RUN_ID = 1234567
EXPECTED = 20  # the receiver's next sequence number of robot 1 (mid-run)
LARGE_BYTES = 50_000


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--pools", type=int, default=50)
    pools = parser.parse_args().pools
    read_ms, large_ms, head_us, sizes, passed = [], [], [], [], []
    for seed in range(pools):
        target = Target("/robot_1/team/updates", TeamUpdate, None)
        messages = ExtremeMessages(random.Random(seed), run_id=RUN_ID)
        for _ in range(POOL_SIZE):
            data = target.next_message(messages)
            sizes.append(len(data))
            started = time.perf_counter()
            dropped = not screen_team_update(
                data, lambda run_id: None if run_id == RUN_ID else "another run",
                only_sender(1), lambda _: EXPECTED).read
            head_us.append((time.perf_counter() - started) * 1e6)
            if not dropped:
                passed.append(len(data))
            started = time.perf_counter()
            try:
                content_problem(deserialize_message(data, TeamUpdate))
            except RMWError:
                pass  # bytes cut short: the middleware refuses them
            elapsed_ms = (time.perf_counter() - started) * 1e3
            read_ms.append(elapsed_ms)
            if len(data) > LARGE_BYTES:
                large_ms.append(elapsed_ms)
    print(f"{len(sizes)} em-fuzz team updates (run id of the run), {min(sizes)}-{max(sizes)} B; "
          f"{len(large_ms)} over {LARGE_BYTES // 1000} kB")
    print(f"deserialize + content_problem: mean {statistics.mean(read_ms):.1f} ms, median "
          f"{statistics.median(read_ms):.2f} ms; over "
          f"{LARGE_BYTES // 1000} kB: median {statistics.median(large_ms):.0f} ms, "
          f"max {max(large_ms):.0f} ms")
    print(f"head screening: median {statistics.median(head_us):.1f} us, max "
          f"{max(head_us):.0f} us; passed to the reader (then deserialized): {len(passed)} "
          f"of {len(sizes)}, the largest {max(passed, default=0)} B")


if __name__ == "__main__":
    main()
