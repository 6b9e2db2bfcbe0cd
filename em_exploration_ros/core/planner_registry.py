"""Planners by name: the Python entry-point group ``em_exploration_ros.planners``.

A planner is found by its name in this group, as Nav2 finds its plugins: the built-in ones
(EM_2, EM_3, CE, BSP, NEAREST) register there in setup.py, and a plugin package registers
its own the same way (docs/plugins.md). Each entry point names a factory, ``module:callable``,
that takes the run's ``ExplorationParams`` and returns a planner
(``core.planning.planner_api.PlannerFactory``); ``core.planning.planners.make_planner``
loads it. Only the names are read here (no plugin is imported), so ``planner.name`` is
checked against the installed planners (``core.params``) without loading any.
"""
from __future__ import annotations

import functools
import importlib.metadata
import sys
from types import MappingProxyType
from typing import Mapping

#: The entry-point group of planners.
PLANNER_GROUP = "em_exploration_ros.planners"
#: The built-in planners, in the order lists show them (installed ones of other names follow,
#: sorted).
BUILT_IN_PLANNERS = ("EM_2", "EM_3", "CE", "BSP", "NEAREST")


def planner_entry_points() -> Mapping[str, importlib.metadata.EntryPoint]:
    """``{name: entry point}`` of every installed planner: the built-in ones first in their
    order, then the others by name. A name two distributions register is the one found
    first on ``sys.path``. Read once per ``sys.path`` (reading every distribution's
    metadata takes a few tenths of a second)."""
    return _entry_points(tuple(sys.path))


def installed_planner_names() -> tuple[str, ...]:
    """Names of every installed planner (``planner_entry_points`` order)."""
    return tuple(planner_entry_points())


@functools.lru_cache(maxsize=4)
def _entry_points(search_path: tuple[str, ...]) -> Mapping[str, importlib.metadata.EntryPoint]:
    """``planner_entry_points`` for the module search path ``search_path``."""
    del search_path  # the cache key: importlib.metadata reads the current sys.path
    found: dict[str, importlib.metadata.EntryPoint] = {}
    for entry in importlib.metadata.entry_points(group=PLANNER_GROUP):
        found.setdefault(entry.name, entry)
    order = ([name for name in BUILT_IN_PLANNERS if name in found]
             + sorted(name for name in found if name not in BUILT_IN_PLANNERS))
    return MappingProxyType({name: found[name] for name in order})
