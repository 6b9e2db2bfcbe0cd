"""``LeanExecutor``: a single-threaded executor that spends less CPU per wake-up.

rclpy's ``SingleThreadedExecutor`` (Jazzy) rebuilds its wait set in Python on every wake-up
(a callback-group check, a context-manager entry and an ``add`` per entity), wraps every
callback in a ``Task`` coroutine, and triggers its own guard condition twice per callback,
which ends its next wait at once, rebuild included, even when nothing else is ready. The
lockstep team wakes its five processes three to five times per simulated step; on this
executor (with two smaller changes of the same day) the default 3-robot run needed 17 % less
CPU (team CPU 36.9 s against 44.6 s, medians of six interleaved pairs; "A leaner executor"
in benchmarks/MEASUREMENTS.md), with the same targets.

``LeanExecutor`` keeps the same contract for the team's nodes and does less:

- the wait set, its entities and their order are built once and rebuilt only when a node's
  entities change (compared by identity at every wake-up). The entities' handles are held
  (entered, as rclpy does around each wait) from that build until the next one or
  ``shutdown``: an entity destroyed meanwhile is freed when it is released;
- a ready subscription or timer whose callback is a plain function is taken and called
  directly, inside its callback group's ``beginning_execution`` / ``ending_execution`` and
  the executor's work tracker, without a ``Task`` and without waking the executor again;
- a future spun until wakes the executor through one done-callback, not one per
  ``spin_once`` as rclpy's (a closure kept per callback run until the future completes);
- everything else (services, clients, node guard conditions, waitables such as liveliness
  events, coroutine callbacks) goes through rclpy's own handler, and while such a handler
  or a future's done-callback is unfinished, the executor works exactly as rclpy's does
  (``SingleThreadedExecutor``'s wake-up), so coroutines and futures behave as documented.

Callbacks run in the order rclpy's executor runs them within one wake-up: waitables, then
per node timers, subscriptions, guard conditions, clients, services, each in the node's
order. One callback runs per ``spin_once``.
"""
from __future__ import annotations

import inspect
import threading
import weakref
from collections import deque
from dataclasses import dataclass
from typing import Any, Callable, Optional, Union

from rclpy.context import Context
from rclpy.executors import (ExternalShutdownException, InvalidHandle,
                             SingleThreadedExecutor, TimeoutObject, timeout_sec_to_nsec)
from rclpy.impl.implementation_singleton import rclpy_implementation as _rclpy
from rclpy.node import Node
from rclpy.subscription import Subscription
from rclpy.task import Future
from rclpy.timer import Timer

#: How a ready entity is run: called directly, or through rclpy's handler with a take.
_DIRECT_SUBSCRIPTION = "subscription"
_DIRECT_TIMER = "timer"

#: The wait-set kinds of rclpy, in the order its executor runs a node's ready entities.
_NODE_KINDS = ("timer", "subscription", "guard_condition", "client", "service")


@dataclass
class _WaitPlan:
    """One wait set for one snapshot of the executor's nodes and their entities."""

    #: ((node, its entities by kind), ...), compared by identity to detect a change
    snapshot: tuple
    wait_set: Any
    #: what the plan holds (entered) while it is in use, so that none is freed under it
    held: list
    #: the handles to add before each wait, by kind: (subscriptions, guard conditions,
    #: timers, clients, services) as ``WaitSet.add_*`` takes them
    to_add: tuple
    #: (waitable, node) pairs (e.g. QoS event handlers); they add themselves
    waitables: list
    #: per node: ((kind, [(pointer, entity, node, how), ...]), ...) in ``_NODE_KINDS`` order
    entries: list


def _node_entities(node: Node) -> tuple:
    """The node's entities that an executor waits on, by kind, in rclpy's order."""
    return (tuple(node.timers), tuple(node.subscriptions), tuple(node.guards),
            tuple(node.clients), tuple(node.services), tuple(node.waitables))


def _hold(entity: Any) -> bool:
    """Enter the entity's handle (released by ``_WaitPlan``'s owner); False once the entity
    is destroyed."""
    try:
        entity.__enter__()
    except InvalidHandle:
        return False
    return True


class LeanExecutor(SingleThreadedExecutor):
    """A ``SingleThreadedExecutor`` with a cached wait set and direct callbacks (see the
    module docstring). One thread spins it; ``shutdown`` (which releases what the wait set
    holds) may come from another."""

    def __init__(self, *, context: Optional[Context] = None) -> None:
        super().__init__(context=context)
        self._plan: _WaitPlan | None = None
        self._ready: deque = deque()
        self._plan_lock = threading.Lock()
        self._waiting = False
        self._release_after_wait = False
        #: an entity was found destroyed (its node may still list it): rebuild the plan
        self._stale = False
        #: futures that already wake this executor when done
        self._waking_futures: weakref.WeakSet[Future] = weakref.WeakSet()

    def spin_once_until_future_complete(
            self, future: Future,
            timeout_sec: Optional[Union[float, TimeoutObject]] = None) -> None:
        """As rclpy's, but ``future`` wakes the executor through one done-callback, added
        the first time: rclpy's adds one at every call, so a process spinning until a future
        completes (every node of the team) kept a closure for every callback it ran, 15 MB
        (144 000 closures) in an evaluator after a 60 s flood of every topic."""
        if future not in self._waking_futures:
            self._waking_futures.add(future)
            future.add_done_callback(lambda _: self.wake())
        self._spin_once_impl(timeout_sec, future.done)

    def shutdown(self, timeout_sec: Optional[float] = None) -> bool:
        with self._plan_lock:
            self._ready.clear()
            if self._waiting:  # the spinning thread releases it when its wait returns
                self._release_after_wait = True
            else:
                self._release_plan()
        return super().shutdown(timeout_sec)

    # ----------------------------------------------------------------- spinning
    def _spin_once_impl(
            self, timeout_sec: Optional[Union[float, TimeoutObject]] = None,
            wait_condition: Callable[[], bool] = lambda: False) -> None:
        if self._unfinished_tasks():
            # rclpy's own wake-up runs (and resumes) tasks before waiting again.
            super()._spin_once_impl(timeout_sec, wait_condition)
            return
        self._cb_iter = None  # a generator left from that path would hold stale readiness
        if not self._ready:
            self._wait(timeout_sec, wait_condition)
        if self._ready:
            self._run(*self._ready.popleft())

    def _unfinished_tasks(self) -> bool:
        """Whether a handler task or a future's callback is still to run; drops done ones."""
        if not self._tasks:
            return False
        with self._tasks_lock:
            self._tasks = [entry for entry in self._tasks if not entry[0].done()]
            return bool(self._tasks)

    def _wait(self, timeout_sec: Optional[Union[float, TimeoutObject]],
              wait_condition: Callable[[], bool]) -> None:
        """Wait once (at most ``timeout_sec``) and queue what became ready."""
        if isinstance(timeout_sec, TimeoutObject):
            timeout_sec = timeout_sec.timeout
        timeout_nsec = timeout_sec_to_nsec(timeout_sec)
        if self._is_shutdown or wait_condition():
            return
        with self._plan_lock:
            plan = self._current_plan()
            self._waiting = True
        try:
            wait_set = plan.wait_set
            wait_set.clear_entities()
            adders = (wait_set.add_subscription, wait_set.add_guard_condition,
                      wait_set.add_timer, wait_set.add_client, wait_set.add_service)
            for add, handles in zip(adders, plan.to_add):
                for handle in handles:
                    add(handle)
            for waitable, _node in plan.waitables:
                waitable.add_to_wait_set(wait_set)
            wait_set.wait(timeout_nsec)
            if self._is_shutdown:
                return
            if not self._context.ok():
                raise ExternalShutdownException()
            self._queue_ready(plan)
        except InvalidHandle:  # a waitable destroyed behind its node's back
            self._stale = True
        finally:
            with self._plan_lock:
                self._waiting = False
                if self._release_after_wait:
                    self._release_after_wait = False
                    self._release_plan()

    def _queue_ready(self, plan: _WaitPlan) -> None:
        """Queue the ready entities of ``plan``'s wait set, in rclpy's order."""
        wait_set = plan.wait_set
        for waitable, node in plan.waitables:
            if waitable.is_ready(wait_set):
                self._ready.append((waitable, node, self._take_waitable))
        ready = {kind: set(wait_set.get_ready_entities(kind)) for kind in _NODE_KINDS}
        for node_entries in plan.entries:
            for kind, entries in node_entries:
                pointers = ready[kind]
                if not pointers:
                    continue
                for pointer, entity, node, how in entries:
                    if pointer in pointers:
                        if kind == "guard_condition":
                            entity._executor_triggered = True
                        self._ready.append((entity, node, how))

    def _run(self, entity: Any, node: Node, how: Any) -> None:
        """Run one ready entity's callback (see the module docstring)."""
        if how is _DIRECT_SUBSCRIPTION or how is _DIRECT_TIMER:
            group = entity.callback_group
            if not group.beginning_execution(entity):
                return
            try:
                with self._work_tracker:
                    if how is _DIRECT_SUBSCRIPTION:
                        self._call_subscription(entity)
                    else:
                        self._call_timer(entity)
            finally:
                group.ending_execution(entity)
            return
        handler = self._make_handler(entity, node, how)
        handler()
        if handler.exception() is not None:
            raise handler.exception()
        handler.result()

    def _call_subscription(self, subscription: Subscription) -> None:
        try:
            with subscription.handle:
                taken = subscription.handle.take_message(subscription.msg_type,
                                                         subscription.raw)
        except InvalidHandle:  # destroyed since the wait
            self._stale = True
            return
        if taken is None:
            return
        if subscription._callback_type is Subscription.CallbackType.MessageOnly:
            subscription.callback(taken[0])
        else:
            subscription.callback(*taken)

    def _call_timer(self, timer: Timer) -> None:
        try:
            with timer.handle:
                if not timer.handle.is_timer_ready():  # cancelled since the wait
                    return
                timer.handle.call_timer()
        except InvalidHandle:  # destroyed since the wait
            self._stale = True
            return
        timer.callback()

    # ----------------------------------------------------------------- the wait plan
    def _current_plan(self) -> _WaitPlan:
        """The cached plan, rebuilt when a node's entities changed since it was made."""
        snapshot = tuple((node, _node_entities(node)) for node in self.get_nodes())
        if self._plan is None or self._stale or self._plan.snapshot != snapshot:
            self._stale = False
            self._release_plan()
            self._plan = self._build_plan(snapshot)
        return self._plan

    def _release_plan(self) -> None:
        """Release what the plan holds (an entity destroyed meanwhile is freed now)."""
        if self._plan is not None:
            for held in reversed(self._plan.held):
                held.__exit__(None, None, None)
            self._plan = None

    def _build_plan(self, snapshot: tuple) -> _WaitPlan:
        """The wait set and run order of ``snapshot``, holding every entity's handle (and the
        context's); entities destroyed already are left out."""
        takes = {"guard_condition": self._take_guard_condition,
                 "client": self._take_client, "service": self._take_service}
        direct = {"timer": (_DIRECT_TIMER, self._take_timer),
                  "subscription": (_DIRECT_SUBSCRIPTION, self._take_subscription)}
        by_kind: dict[str, list] = {kind: [] for kind in _NODE_KINDS}
        held, waitables, entries = [], [], []
        for node, entities in snapshot:
            node_entries = []
            for kind, kind_entities in zip(_NODE_KINDS, entities):
                kind_entries = []
                for entity in kind_entities:
                    if not _hold(entity.handle):
                        continue
                    held.append(entity.handle)
                    if kind in direct:
                        plain, take = direct[kind]
                        how = take if inspect.iscoroutinefunction(entity.callback) else plain
                    else:
                        how = takes[kind]
                    by_kind[kind].append(entity.handle)
                    kind_entries.append((entity.handle.pointer, entity, node, how))
                node_entries.append((kind, kind_entries))
            entries.append(node_entries)
            for waitable in entities[len(_NODE_KINDS)]:
                if _hold(waitable):
                    held.append(waitable)
                    waitables.append((waitable, node))
        # The executor's own guard conditions (wake(), Ctrl-C) only end the wait.
        for guard in (self._guard, self._sigint_gc):
            if _hold(guard.handle):
                held.append(guard.handle)
                by_kind["guard_condition"].append(guard.handle)
        if _hold(self._context.handle):
            held.append(self._context.handle)
        to_add = tuple(by_kind[kind] for kind in
                       ("subscription", "guard_condition", "timer", "client", "service"))
        counts = [len(handles) for handles in to_add] + [0]
        for waitable, _node in waitables:
            extra = waitable.get_num_entities()
            for index, count in enumerate((extra.num_subscriptions, extra.num_guard_conditions,
                                           extra.num_timers, extra.num_clients,
                                           extra.num_services, extra.num_events)):
                counts[index] += count
        return _WaitPlan(snapshot=snapshot,
                         wait_set=_rclpy.WaitSet(*counts, self._context.handle),
                         held=held, to_add=to_add, waitables=waitables, entries=entries)


def spin(node: Node, until: Future | None = None) -> None:
    """Run ``node``'s callbacks on a ``LeanExecutor`` until ROS shuts down, the executor is
    shut down or ``until`` (when given) completes; the executor is shut down after."""
    executor = LeanExecutor(context=node.context)
    executor.add_node(node)
    try:
        if until is None:
            executor.spin()
        else:
            executor.spin_until_future_complete(until)
    finally:
        executor.shutdown()
