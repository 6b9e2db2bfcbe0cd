"""Team traffic on the wire: bytes per simulated second each robot publishes as TeamUpdate.

Runs em-sim's team in process (``TeamRunner``, the same agents, decisions and lockstep
timing as the ROS system), converts every TeamUpdate a robot publishes with the ROS
conversions of the robot node and serializes it with ``rclpy.serialization`` (CDR, with
its 4-byte encapsulation header: the payload DDS carries). Prints per robot: updates,
CDR bytes, bytes per simulated second, and where the bytes go: each array field of
TeamUpdate (the bytes the message loses when that array is emptied) and, inside the
keyframes, each array of Keyframe; the rest is the update's fixed part.

The RTPS overhead per message is stated apart (``RTPS_BYTES_PER_MESSAGE``: the RTPS header,
INFO_TS and the DATA submessage header of one sample, from the RTPS 2.x specification;
without UDP/IP headers, discovery, heartbeats and acknowledgements). Re-sends after a gap
do not happen in em-sim (no loss), so the figures are the stream itself.

Usage: ``python benchmarks/team_traffic.py [--seed 0] [em-sim run options]``.
"""
from __future__ import annotations

import argparse
from collections import Counter, defaultdict
from typing import Any, Sequence

from rclpy.serialization import serialize_message

from em_exploration_ros.core.records.team_data import TeamUpdate
from em_exploration_ros.core.records.team_wire import TeamWireFormat
from em_exploration_ros.core.sessions.team_runner import TeamRunner
from em_exploration_ros.nodes.conversions import team_update_to_msg
from em_exploration_ros.tools.sim_cli import add_run_arguments, params_from_args

#: RTPS header (20) + INFO_TS submessage (12) + DATA submessage header (24) per sample.
RTPS_BYTES_PER_MESSAGE = 20 + 12 + 24


def cdr_size(message: Any) -> int:
    """Bytes of ``message`` serialized as CDR (encapsulation header included)."""
    return len(serialize_message(message))


def array_fields(message: Any) -> list[str]:
    """Names of the fields of ``message`` that are unbounded arrays of messages."""
    return [name for name, kind in message.get_fields_and_field_types().items()
            if kind.startswith("sequence<") and "/" in kind]


def bytes_by_array(message: Any) -> dict[str, int]:
    """For each message array of ``message``: how many bytes it adds to the CDR size (the
    size with the array minus the size with the array emptied; alignment padding counts
    where it falls)."""
    total = cdr_size(message)
    shares = {}
    for name in array_fields(message):
        items = getattr(message, name)
        setattr(message, name, [])
        shares[name] = total - cdr_size(message)
        setattr(message, name, items)
    return shares


def keyframe_bytes_by_array(message: Any) -> dict[str, int]:
    """Bytes of the readings inside the keyframes of one TeamUpdate message, per array of
    Keyframe (the same difference as ``bytes_by_array``, over all its keyframes)."""
    shares: Counter[str] = Counter()
    for keyframe in message.keyframes:
        total = cdr_size(message)
        for name in array_fields(keyframe):
            items = getattr(keyframe, name)
            setattr(keyframe, name, [])
            shares[name] += total - cdr_size(message)
            setattr(keyframe, name, items)
    return dict(shares)


class TrafficMeter:
    """Collects the CDR size of every TeamUpdate per robot, with its breakdown."""

    def __init__(self) -> None:
        self.messages: Counter[int] = Counter()
        self.total: Counter[int] = Counter()
        self.by_array: dict[int, Counter[str]] = defaultdict(Counter)

    def add(self, update: TeamUpdate, message: Any) -> None:
        robot = update.robot_id
        self.messages[robot] += 1
        size = cdr_size(message)
        self.total[robot] += size
        shares = bytes_by_array(message)
        inside = keyframe_bytes_by_array(message)
        self.by_array[robot].update({f"keyframes.{k}": v for k, v in inside.items()})
        shares["keyframes"] -= sum(inside.values())
        self.by_array[robot].update(shares)
        self.by_array[robot]["fixed part"] += size - sum(shares.values()) - sum(inside.values())


def metered_run(runner: TeamRunner, meter: TrafficMeter, convert: Any) -> None:
    """Run ``runner`` to its stop rule, feeding every published update to ``meter`` (each
    agent's ``take_outgoing`` is wrapped; nothing else changes)."""
    for agent in runner.agents:
        take = agent.take_outgoing

        def metered(take=take) -> TeamUpdate | None:
            update = take()
            if update is not None:
                meter.add(update, convert(update))
            return update

        agent.take_outgoing = metered
    runner.run()


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    add_run_arguments(parser)
    parser.add_argument("--seed", type=int, default=0, help="seed of world and noise")
    args = parser.parse_args(argv)
    params = params_from_args(args, args.seed)
    runner = TeamRunner(params)
    meter = TrafficMeter()
    wire = TeamWireFormat(params)
    metered_run(runner, meter, lambda update: team_update_to_msg(update, wire))
    sim_s = runner.simulation.stamp_s
    summary = runner.monitor
    print(f"seed {args.seed}, {params.world.num_robots} robots, {params.planner.name}: "
          f"{sim_s:.1f} s simulated ({summary.stop_reason}), "
          f"{runner.num_decisions} decisions")
    print("robot  updates  CDR bytes  CDR B/s  +RTPS B/s")
    for robot in sorted(meter.total):
        rate = meter.total[robot] / sim_s
        rtps = meter.messages[robot] * RTPS_BYTES_PER_MESSAGE / sim_s
        print(f"{robot:5d}  {meter.messages[robot]:7d}  {meter.total[robot]:9d}  "
              f"{rate:7.1f}  {rtps:9.1f}")
    print("CDR bytes per simulated second, by part:")
    parts = sorted({part for shares in meter.by_array.values() for part in shares})
    print(f"  {'part':22s}" + "".join(f"  robot {r:d}" for r in sorted(meter.total)))
    for part in parts:
        print(f"  {part:22s}" + "".join(f"  {meter.by_array[r][part] / sim_s:7.1f}"
                                        for r in sorted(meter.total)))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
