"""Names of the team-data topics that the link relay (``nodes/team_relay.py``) and the
robots share; a module of its own so that a robot process need not import the relay (and,
through it, the world's simulation)."""
from __future__ import annotations

from em_exploration_ros.nodes.conversions import robot_namespace

REQUESTS_TOPIC = "/team/update_requests"
LINK_COUNTS_TOPIC = "/world/link_counts"


def delivered_updates_topic(robot: int) -> str:
    """Where the relay delivers team records to ``robot``."""
    return f"/{robot_namespace(robot)}/team/delivered_updates"


def history_copies_topic(robot: int) -> str:
    """Where ``robot`` sends, in relay mode, its copies of a restarted teammate's records."""
    return f"/{robot_namespace(robot)}/team/history_copies"


def delivered_requests_topic(robot: int) -> str:
    """Where the relay delivers requests for ``robot``'s records."""
    return f"/{robot_namespace(robot)}/team/delivered_requests"
