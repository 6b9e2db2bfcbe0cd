"""The common life cycle of the system's node processes (the ``main()`` of each node).

Start rclpy, build the node, spin until Ctrl-C / SIGTERM / shutdown (or until the node's
own ``done`` future completes), then let the node wrap up, destroy it and shut down. A
node that refuses its parameters (``ValueError`` or one of rclpy's ``ParameterException``s
from its constructor: wrong type, outside the declared range) ends the process with exit
code 2 and one fatal log line, no traceback. Only the constructor's errors mean bad
parameters: an exception while spinning is not turned into exit code 2.
"""
from __future__ import annotations

from typing import Callable, TypeVar

import rclpy
from rclpy.exceptions import ParameterException
from rclpy.executors import ExternalShutdownException
from rclpy.impl.implementation_singleton import rclpy_implementation
from rclpy.node import Node

#: The error rclpy raises when a call into its C library fails (e.g. publishing after the
#: context was shut down).
RCLError = rclpy_implementation.RCLError

EXIT_BAD_PARAMETERS = 2

NodeType = TypeVar("NodeType", bound=Node)


def run_node(make_node: Callable[[], NodeType], logger_name: str,
             args: list[str] | None = None,
             wrap_up: Callable[[NodeType], int] | None = None) -> int:
    """Run one node process; returns its exit code.

    ``wrap_up(node)`` runs after the spin ends, whatever ended it, and returns the exit
    code (default 0). A node with a ``done`` future spins until it completes.
    """
    rclpy.init(args=args)
    node = None
    try:
        try:
            node = make_node()
        except (ValueError, ParameterException) as error:
            rclpy.logging.get_logger(logger_name).fatal(f"cannot start: {error}")
            return EXIT_BAD_PARAMETERS
        done = getattr(node, "done", None)
        if done is None:
            rclpy.spin(node)
        else:
            rclpy.spin_until_future_complete(node, done)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except RCLError:
        if rclpy.ok():
            raise
        # A callback published while Ctrl-C / SIGTERM shut the context down: a shutdown.
    finally:
        code = 0
        if node is not None:
            if wrap_up is not None:
                code = wrap_up(node)
            node.destroy_node()
        rclpy.try_shutdown()
    return code
