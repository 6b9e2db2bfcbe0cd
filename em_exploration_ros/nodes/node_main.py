"""The common life cycle of the system's node processes (the ``main()`` of each node).

Start rclpy (on a participant id of the process's own when Fast DDS would give it a dead
process's: ``participant_id``), build the node, spin until Ctrl-C / SIGTERM / shutdown (or
until the node's own ``done`` future completes), handing the memory it freed back to the
system now and then (``memory_return``), then let the node wrap up, destroy it and shut
down. While it spins and wraps up, the ROS-free core's Python log records go to the node's
ROS logger (``core_log``). A
node that refuses its parameters (``ValueError`` or one of rclpy's ``ParameterException``s
from its constructor: wrong type, outside the declared range) ends the process with exit
code 2 and one fatal log line, no traceback. Only the constructor's errors mean bad
parameters: an exception while spinning is not turned into exit code 2.

Ctrl-C (SIGINT) ends a node the way SIGTERM does: rclpy's own signal handler shuts the
context down and the spin returns. Python's default SIGINT handler is replaced for the
process's ROS life (``interrupt_shuts_down``), because the ``KeyboardInterrupt`` it raises
lands wherever the main thread happens to be, including inside rclpy's C++ conversion of a
message being taken, which then fails with an unrelated ``RuntimeError`` ("Unable to convert
call argument '0' to Python object") and exit code 1: 2 of 50 SIGINTs of a loaded world
process did that.
"""
from __future__ import annotations

import signal
from contextlib import contextmanager
from typing import Callable, Iterator, TypeVar

import rclpy
from rclpy.context import Context
from rclpy.exceptions import ParameterException
from rclpy.executors import ExternalShutdownException
from rclpy.impl.implementation_singleton import rclpy_implementation
from rclpy.node import Node

from em_exploration_ros.nodes import lean_executor
from em_exploration_ros.nodes.core_log import core_logs_to
from em_exploration_ros.nodes.memory_return import return_freed_memory
from em_exploration_ros.nodes.participant_id import ParticipantProfile, own_participant_id

#: The error rclpy raises when a call into its C library fails (e.g. publishing after the
#: context was shut down).
RCLError = rclpy_implementation.RCLError

EXIT_BAD_PARAMETERS = 2

NodeType = TypeVar("NodeType", bound=Node)


@contextmanager
def interrupt_shuts_down() -> Iterator[Callable[[], bool]]:
    """Within the block, SIGINT raises no ``KeyboardInterrupt``; it only shuts ROS down.

    rclpy's handler (installed by ``rclpy.init`` inside the block) shuts every context down
    and then calls the handler it replaced, which is this one: it only notes the signal.
    Yields a function telling whether a SIGINT has arrived, for the moments when rclpy's
    handler is not installed yet (before ``rclpy.init``). Must run in the main thread.
    """
    received: list[int] = []
    previous = signal.signal(signal.SIGINT, lambda signum, _frame: received.append(signum))
    try:
        yield lambda: bool(received)
    finally:
        signal.signal(signal.SIGINT, previous)


def run_node(make_node: Callable[[], NodeType], logger_name: str,
             args: list[str] | None = None,
             wrap_up: Callable[[NodeType], int] | None = None) -> int:
    """Run one node process; returns its exit code.

    ``wrap_up(node)`` runs after the spin ends, whatever ended it, and returns the exit
    code (default 0). A node with a ``done`` future spins until it completes.
    """
    with interrupt_shuts_down() as interrupted, own_participant_id() as participant:
        rclpy.init(args=args)
        if interrupted():  # Ctrl-C before rclpy's handler was in place
            rclpy.try_shutdown()
            return 0
        return _spin_node(make_node, logger_name, wrap_up, participant)


def first_node(make_node: Callable[[], NodeType], participant: ParticipantProfile
               ) -> NodeType:
    """The process's first node, made while ``participant``'s profile is in place (its
    participant is made with it: ``participant_id``); the profile is released after, and
    its line logged by the node."""
    try:
        node = make_node()
    finally:
        participant.release()
    if participant.line is not None:
        node.get_logger().info(participant.line)
    return node


def _spin_node(make_node: Callable[[], NodeType], logger_name: str,
               wrap_up: Callable[[NodeType], int] | None,
               participant: ParticipantProfile) -> int:
    """``run_node`` after ``rclpy.init``: build (the participant with it), spin, wrap up,
    shut down."""
    node = None
    try:
        try:
            node = first_node(make_node, participant)
        except (ValueError, ParameterException) as error:
            rclpy.logging.get_logger(logger_name).fatal(f"cannot start: {error}")
            return EXIT_BAD_PARAMETERS
        return_freed_memory(node)
        with core_logs_to(node.get_logger()):
            lean_executor.spin(node, until=getattr(node, "done", None))
    except ExternalShutdownException:
        pass
    except RCLError:
        if rclpy.ok():
            raise
        # A callback published while Ctrl-C / SIGTERM shut the context down: a shutdown.
    finally:
        code = 0
        if node is not None:
            _console_logging_after_signal(node.context)
            if wrap_up is not None:
                with core_logs_to(node.get_logger()):
                    code = wrap_up(node)
            node.destroy_node()
        rclpy.try_shutdown()
    return code


def _console_logging_after_signal(context: Context) -> None:
    """After Ctrl-C / SIGTERM, log to the console only.

    rclpy's signal handler shuts the context down in C, which, unlike ``Context.shutdown``,
    leaves rcl's /rosout logging on with a publisher that can no longer publish, so every
    line a node logs while wrapping up also printed "Failed to publish log message to
    rosout: publisher's context is invalid". This ends that logging as ``Context.shutdown``
    would (the private ``_logging_fini``, under the context's lock, as rclpy calls it); the
    console and log files keep every line.
    """
    if context.ok():
        return
    with context._lock:  # noqa: SLF001 (rclpy's own shutdown path, see docstring)
        context._logging_fini()  # noqa: SLF001
