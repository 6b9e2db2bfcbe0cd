"""``LeanNode``: the base of the team's own nodes (em-world, em-robot, em-evaluator).

rclpy gives every subscription and publisher two QoS-event handlers by default (incompatible
QoS, incompatible type: a warning when a foreign endpoint does not match). Each handler is a
waitable that the executor visits in Python on every wake-up, and the lockstep team wakes its
five processes many times per step: in the default 3-robot run these idle handlers took
about a fifth of the team's CPU (48-50 CPU-s with them off against 60 with them on, same
targets). The team's topics use the profiles of ``nodes/qos.py`` on both ends, so a mismatch
can only come from a foreign node, which warns on its side (``ros2 topic echo`` / ``pub``
do). Handlers a node asks for (liveliness, ``nodes/liveliness.py``) are kept.
"""
from __future__ import annotations

from typing import Any

from rclpy.event_handler import PublisherEventCallbacks, SubscriptionEventCallbacks
from rclpy.node import Node
from rclpy.publisher import Publisher
from rclpy.subscription import Subscription


class LeanNode(Node):
    """A Node whose subscriptions and publishers get no default QoS-event handlers (see
    module docstring); explicit ``event_callbacks`` are used as given."""

    def create_subscription(self, *args: Any, **kwargs: Any) -> Subscription:
        kwargs.setdefault("event_callbacks",
                          SubscriptionEventCallbacks(use_default_callbacks=False))
        return super().create_subscription(*args, **kwargs)

    def create_publisher(self, *args: Any, **kwargs: Any) -> Publisher:
        kwargs.setdefault("event_callbacks", PublisherEventCallbacks(use_default_callbacks=False))
        return super().create_publisher(*args, **kwargs)
