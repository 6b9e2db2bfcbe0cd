"""Algorithm 1 of the paper (the EM step): covariances after a candidate's virtual measurements.

The virtual paths and measurements themselves (``X_predict``, ``X_next``) are built by
``em_scenario``. Virtual measurements have zero residual, so the means do not move; only
the covariances change. All pose covariances here are in the GTSAM ``Pose2`` tangent
(body) frame.

Fast path. The teammates' part (``X_predict`` with its measurements) is the same for every
candidate of a decision, so :class:`DecisionFactorization` adds it to the team graph,
linearizes once at the current estimate and factors once: teammates' other poses are
eliminated (COLAMD), then the rest with the boundary ``B`` last. ``B`` holds what the
candidates' own measurements (``X_next``: alpha's path, its landmark readings and its
readings with teammates) touch: alpha's latest pose, landmarks, teammates' latest poses or
predicted waypoints. The tracked poses (alpha's history for EM, predicted waypoints for
BSP) are eliminated first, in their order, except those linked to a non-adjacent tracked
pose (through an eliminated teammate path); with them, the landmarks and ``B`` last they
form the hub ``H``. This gives ``P = Sigma_BB`` (from the hub's square-root block
``R_HH``), and the tracked poses' marginals ``Sigma_ii`` and cross-covariances
``C_i = Sigma_iB`` by one backward recursion along the chain (selected inversion,
:func:`_chain_selected_inverse`). Many meetings make the hub large and dense; above
``DENSE_HUB_MAX_DIM`` the same covariances come instead from a selected inversion of the
whole graph's sparse factorization (:func:`_sparse_selected_inverse`). Per candidate
(:meth:`propagate`) only small dense algebra remains: the whitened Jacobian ``[J_W J_B]``
of ``X_next``'s measurements is QR-factored with alpha's new waypoints ``W`` first, leaving
``R_WW``, ``R_WB`` and the square root ``U^T`` of the information added to ``B``
(``Delta = U U^T``). With
``M = I + U^T P U`` (Woodbury)::

    P'         = P - P U M^-1 U^T P
    Sigma'_ii  = Sigma_ii - C_i U M^-1 U^T C_i^T
    x_W        = K x_B + e,  K = -R_WW^-1 R_WB,  e ~ N(0, (R_WW^T R_WW)^-1)
    Sigma'_WW  = K P' K^T + R_WW^-1 R_WW^-T

which is exact for the linearized problem. ``em_oracle.propagate_oracle`` is the direct
version (copy the graph, add every virtual factor, ``gtsam.Marginals``).
"""
from __future__ import annotations

import itertools
import logging
from dataclasses import dataclass
from typing import Callable, Iterable, Sequence, TypeVar

import gtsam
import numpy as np
from numpy.typing import NDArray

from em_exploration_ros.core.planning.em_scenario import (TeamSnapshot, VirtualFactors,
                                                          VirtualScenario, graph_with_virtual)
from em_exploration_ros.core.slam.team_slam import is_landmark_key, landmark_key_mask

_LOG = logging.getLogger(__name__)
T = TypeVar("T")

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]


def _key_dim(key: int) -> int:
    """Tangent dimension of a team-graph variable: 2 for a landmark, 3 for a pose."""
    return 2 if is_landmark_key(key) else 3


def _key_dims(keys: Sequence[int]) -> IntArray:
    """:func:`_key_dim` of many keys, ``(K,)``."""
    return np.where(landmark_key_mask(np.asarray(keys, dtype=np.int64).reshape(-1)), 2, 3)


@dataclass(frozen=True)
class PropagationResult:
    """Marginal covariances after the virtual measurements (GTSAM tangent frame).

    ``history_covariances`` (K, 3, 3): the deciding robot's graph poses
    (``TeamSnapshot.history_keys`` order); ``predicted_covariances`` (n_p, 3, 3) and
    ``next_covariances`` (n_n, 3, 3): the waypoints of ``scenario.predicted`` and
    ``scenario.next`` in their key order. A part that was not requested is empty.
    """

    history_covariances: FloatArray
    predicted_covariances: FloatArray
    next_covariances: FloatArray


def _adjoint_inverse(poses: FloatArray) -> FloatArray:
    """``Ad(T^-1)`` (F, 3, 3) of relative poses ``T`` (F, 3): GTSAM Pose2 adjoint maps."""
    x, y, theta = poses[:, 0], poses[:, 1], poses[:, 2]
    cos_t, sin_t = np.cos(theta), np.sin(theta)
    adjoint = np.zeros((len(poses), 3, 3))
    adjoint[:, 0, 0] = cos_t
    adjoint[:, 0, 1] = sin_t
    adjoint[:, 1, 0] = -sin_t
    adjoint[:, 1, 1] = cos_t
    adjoint[:, 0, 2] = sin_t * x - cos_t * y
    adjoint[:, 1, 2] = cos_t * x + sin_t * y
    adjoint[:, 2, 2] = 1.0
    return adjoint


def _bearing_range_jacobians(poses: FloatArray,
                             points: FloatArray) -> tuple[FloatArray, FloatArray]:
    """GTSAM ``BearingRangeFactor2D`` Jacobians ``(F, 2, 3)`` w.r.t. the pose (tangent) and
    ``(F, 2, 2)`` w.r.t. the point, rows (bearing, range)."""
    cos_t, sin_t = np.cos(poses[:, 2]), np.sin(poses[:, 2])
    d = points - poses[:, :2]
    qx = cos_t * d[:, 0] + sin_t * d[:, 1]
    qy = -sin_t * d[:, 0] + cos_t * d[:, 1]
    r2 = qx * qx + qy * qy
    r = np.sqrt(r2)
    pose_jacobian = np.zeros((len(poses), 2, 3))
    pose_jacobian[:, 0, 0] = qy / r2
    pose_jacobian[:, 0, 1] = -qx / r2
    pose_jacobian[:, 0, 2] = -1.0
    pose_jacobian[:, 1, 0] = -qx / r
    pose_jacobian[:, 1, 1] = -qy / r
    point_jacobian = np.empty((len(poses), 2, 2))
    point_jacobian[:, 0, 0] = (-qy * cos_t - qx * sin_t) / r2
    point_jacobian[:, 0, 1] = (-qy * sin_t + qx * cos_t) / r2
    point_jacobian[:, 1, 0] = d[:, 0] / r
    point_jacobian[:, 1, 1] = d[:, 1] / r
    return pose_jacobian, point_jacobian


def _scatter(matrix: FloatArray, row_start: int, columns: Sequence[IntArray],
             blocks: Sequence[FloatArray]) -> int:
    """Write factor blocks (F, rows, dim) at consecutive row blocks from ``row_start`` and
    column offsets (F,) per variable; returns the next free row."""
    count, rows = blocks[0].shape[:2]
    row_index = row_start + np.arange(count)[:, None] * rows + np.arange(rows)[None, :]
    for column, block in zip(columns, blocks):
        column_index = column[:, None] + np.arange(block.shape[2])[None, :]
        matrix[row_index[:, :, None], column_index[:, None, :]] = block
    return row_start + count * rows


def _whitened_jacobian(factors: VirtualFactors, columns_of: Callable[[IntArray], IntArray],
                       num_columns: int) -> FloatArray:
    """Whitened Jacobian (rows: odometry, robot readings, landmark readings) of the
    factors at zero residual; ``columns_of`` maps keys to their first column."""
    pose_factors = (factors.odometry, factors.robot_observations)
    observations = factors.landmark_observations
    rows = 3 * sum(len(f.key1) for f in pose_factors) + 2 * len(observations.pose_key)
    jacobian = np.zeros((rows, num_columns))
    row = 0
    for part in pose_factors:
        if len(part.key1):
            first = -part.sqrt_information @ _adjoint_inverse(part.measured)
            row = _scatter(jacobian, row, [columns_of(part.key1), columns_of(part.key2)],
                           [first, np.asarray(part.sqrt_information)])
    if len(observations.pose_key):
        pose_jacobian, point_jacobian = _bearing_range_jacobians(observations.pose,
                                                                 observations.point)
        roots = observations.sqrt_information
        _scatter(jacobian, row,
                 [columns_of(observations.pose_key), columns_of(observations.landmark_key)],
                 [roots @ pose_jacobian, roots @ point_jacobian])
    return jacobian


def _retry_if_indeterminate(first: Callable[[], T], fallback: Callable[[], T]) -> T:
    """``first()``, or ``fallback()`` if GTSAM finds the linear system indeterminate.

    The team graph is badly conditioned (the anchor's 1e-6 rad prior) and GTSAM's default
    Cholesky elimination occasionally fails on it where QR, which iSAM2 uses, does not.
    QR every time would cost about 60 % more per decision, so it is the fallback only.
    """
    try:
        return first()
    except RuntimeError as error:
        if "indeterminate" not in str(error).lower():
            raise
        _LOG.warning("linear system indeterminate for Cholesky (%s...); using the fallback",
                     str(error).splitlines()[0][:80])
        return fallback()


class _KeyLayout:
    """Where variables sit in a dense vector: ``keys`` in order, each taking its tangent
    dimension (3 per pose, 2 per landmark) from ``offsets``."""

    def __init__(self, keys: Sequence[int]) -> None:
        self.keys = np.asarray(keys, dtype=np.int64).reshape(-1)
        dims = _key_dims(self.keys)
        self.offsets = (np.cumsum(dims) - dims).astype(np.int64)
        self.dim = int(dims.sum())
        self._order = np.argsort(self.keys)

    def index_of(self, keys: IntArray) -> IntArray:
        """Position (K,) of each of ``keys`` in the layout, -1 for a key not in it."""
        keys = np.asarray(keys, dtype=np.int64).reshape(-1)
        if not len(self.keys):
            return np.full(len(keys), -1, dtype=np.int64)
        found = self._order[np.minimum(np.searchsorted(self.keys, keys, sorter=self._order),
                                       len(self.keys) - 1)]
        return np.where(self.keys[found] == keys, found, -1)

    def first_columns(self, keys: IntArray) -> IntArray:
        """First column (K,) of each of ``keys``; every key must be in the layout."""
        index = self.index_of(keys)
        if np.any(index < 0):
            raise ValueError("a variable is missing from the layout")
        return self.offsets[index]

    def columns(self, keys: IntArray) -> IntArray:
        """Every column of ``keys``, key by key."""
        keys = np.asarray(keys, dtype=np.int64).reshape(-1)
        return _expand_columns(self.first_columns(keys), _key_dims(keys))


def _expand_columns(first: IntArray, dims: IntArray) -> IntArray:
    """``first[i], first[i] + 1, ..., first[i] + dims[i] - 1`` for every i, concatenated."""
    total = int(dims.sum())
    return np.repeat(first, dims) + np.arange(total) - np.repeat(np.cumsum(dims) - dims, dims)


def _index_ranges(blocks: Iterable[tuple[int, int]]) -> list[int]:
    """``start, start + 1, ..., start + dim - 1`` of every ``(start, dim)``, concatenated:
    :func:`_expand_columns` for a few blocks, in plain Python."""
    return [index for start, dim in blocks for index in range(start, start + dim)]


def _conditionals_by_key(bayes_net: gtsam.GaussianBayesNet) -> dict[int, gtsam.GaussianConditional]:
    """The conditionals of a sequential Bayes net by frontal key (GTSAM emits them per
    connected component, not always in elimination order)."""
    conditionals = (bayes_net.at(index) for index in range(bayes_net.size()))
    return {conditional.firstFrontalKey(): conditional for conditional in conditionals}


def _hub_root(conditionals: dict[int, gtsam.GaussianConditional], hub: _KeyLayout) -> FloatArray:
    """Upper-triangular square-root information ``R_HH`` (D, D) of the hub's marginal, from
    the conditionals of the hub variables (eliminated last, so their parents are in it).

    Conditionals with the same frontal dimension are scattered together: their ``[R S]``
    blocks side by side, each column sent to its variable's column."""
    root = np.zeros((hub.dim, hub.dim))
    frontal_dims = _key_dims(hub.keys)
    for frontal_dim in (2, 3):
        group = frontal_dims == frontal_dim
        if not np.any(group):
            continue
        members = [conditionals[key] for key in hub.keys[group].tolist()]
        keys = [conditional.keys() for conditional in members]
        flat = np.fromiter(itertools.chain.from_iterable(keys), dtype=np.int64)
        first_row = np.repeat(hub.offsets[group], [len(k) for k in keys])
        dims = _key_dims(flat)
        blocks = np.concatenate([block for conditional in members
                                 for block in (conditional.R(), conditional.S())], axis=1)
        rows = np.repeat(first_row, dims)[:, None] + np.arange(frontal_dim)
        root[rows, _expand_columns(hub.first_columns(flat), dims)[:, None]] = blocks.T
    return root


def _covariance_of_root(root: FloatArray) -> FloatArray:
    """``(R^T R)^-1`` (symmetric) of an upper-triangular square-root information ``R``."""
    inverse_root = np.linalg.inv(root)
    covariance = inverse_root @ inverse_root.T
    return 0.5 * (covariance + covariance.T)


def _chain_selected_inverse(chain: Sequence[int],
                            conditionals: dict[int, gtsam.GaussianConditional],
                            hub: _KeyLayout, hub_covariance: FloatArray
                            ) -> tuple[FloatArray, FloatArray]:
    """Marginal covariances ``Sigma_kk`` (m, 3, 3) and hub cross-covariances ``Sigma_kH``
    (m, 3, D) of chain poses eliminated first, in order, before the hub.

    Pose k's conditional ``R_kk x_k + S_k [x_k+1; x_H] = d`` has as parents at most the next
    chain pose and hub variables. With ``[a_k h_k] = -R_kk^-1 S_k`` (zero columns for
    absent parents), the inverse's recursion from the last chain pose backwards is::

        Sigma_kH = a_k Sigma_k+1,H + h_k Sigma_HH
        Sigma_kk = R_kk^-1 R_kk^-T + a_k Sigma_k+1,k+1 a_k^T + h_k Sigma_HH h_k^T
                   + a_k Sigma_k+1,H h_k^T + (a_k Sigma_k+1,H h_k^T)^T

    (the parents' joint covariance sandwiched by the gain), exact for the linear system.
    The parts that do not depend on the previous pose are batched over the chain.
    """
    count = len(chain)
    if count == 0:
        return np.zeros((0, 3, 3)), np.zeros((0, 3, hub.dim))
    chain_conditionals = [conditionals[key] for key in chain]
    parents = [conditional.keys()[1:] for conditional in chain_conditionals]
    flat = np.fromiter(itertools.chain.from_iterable(parents), dtype=np.int64)
    owner = np.repeat(np.arange(count), [len(p) for p in parents])
    next_key = np.array(list(chain[1:]) + [-1], dtype=np.int64)
    is_next = flat == next_key[owner]
    first = np.zeros(len(flat), dtype=np.int64)
    first[~is_next] = 3 + hub.first_columns(flat[~is_next])
    dims = _key_dims(flat)
    gains = np.zeros((count, 3, 3 + hub.dim))  # columns: next chain pose, then the hub
    gains[np.repeat(owner, dims), :, _expand_columns(first, dims)] = np.concatenate(
        [conditional.S() for conditional in chain_conditionals], axis=1).T
    inverse_roots = np.linalg.inv(np.array([conditional.R() for conditional in chain_conditionals]))
    gains = -inverse_roots @ gains
    to_next, to_hub = gains[:, :, :3], gains[:, :, 3:]
    from_hub = (to_hub.reshape(-1, hub.dim) @ hub_covariance).reshape(count, 3, hub.dim)
    rows = _backward_scan(to_next, from_hub, sandwich=False)
    below = np.concatenate([rows[1:], np.zeros((1, 3, hub.dim))])
    mixed = to_next @ below @ np.swapaxes(to_hub, 1, 2)
    own = (inverse_roots @ np.swapaxes(inverse_roots, 1, 2) + mixed + np.swapaxes(mixed, 1, 2)
           + from_hub @ np.swapaxes(to_hub, 1, 2))
    marginals = _backward_scan(to_next, own, sandwich=True)
    return 0.5 * (marginals + np.swapaxes(marginals, 1, 2)), rows


def _backward_scan(gains: FloatArray, terms: FloatArray, sandwich: bool) -> FloatArray:
    """Solve ``y_k = terms_k + gains_k y_k+1`` (or ``+ gains_k y_k+1 gains_k^T`` with
    ``sandwich``) for k = n - 1 .. 0 with ``y_n = 0``: gains (n, 3, 3), terms (n, 3, c).

    By recursive doubling (Hillis-Steele): after round j, ``y_k = terms_k + G_k y_k+2^j
    (G_k^T)`` with ``G_k`` the product of the 2^j gains from k on, so log2(n) batched
    rounds replace n small Python-level products.
    """
    count = len(terms)
    terms, gains = terms.copy(), gains.copy()
    span = 1
    while span < count:
        later = terms[span:]
        reached = gains[:-span] @ later
        if sandwich:
            reached = reached @ np.swapaxes(gains[:-span], 1, 2)
        terms[:-span] += reached
        gains[:-span] = gains[:-span] @ gains[span:]
        gains[-span:] = 0.0
        span *= 2
        if not gains.any():  # every chain segment is shorter than span
            break
    return terms


#: Hub dimension above which :class:`DecisionFactorization` leaves the chain-and-hub method
#: for :func:`_sparse_selected_inverse`. The hub is dense: its cost grows with the cube of
#: its dimension, while the sparse method's grows with the number of variables. Many meetings
#: make the hub large (700-1047 late in a 200 m EM_2 mission with 20 rendezvous); in the
#: default 100 m mission it stays under 200. At 300-400 both methods cost about the same.
DENSE_HUB_MAX_DIM = 400


@dataclass(frozen=True)
class _EliminationTree:
    """The non-boundary variables of a sequential Bayes net, from the last eliminated to the
    first, that :func:`_sparse_selected_inverse` visits: the tracked ones and their
    ancestors. ``parents[j]``: j's parents in its conditional's order; ``outside[j]``: those
    outside the boundary; ``first_parent[j]``: the first eliminated of them (j's parent in
    the tree); ``children[j]``: how many visited variables have j as ``first_parent``."""

    visit: list[int]
    parents: dict[int, list[int]]
    outside: dict[int, list[int]]
    first_parent: dict[int, int]
    children: dict[int, int]

    @classmethod
    def build(cls, order: Sequence[int], conditionals: dict[int, gtsam.GaussianConditional],
              boundary: set[int], tracked: set[int]) -> "_EliminationTree":
        position = {key: index for index, key in enumerate(order)}
        parents = {key: list(conditionals[key].keys())[1:] for key in order}
        outside = {key: [p for p in parents[key] if p not in boundary] for key in order}
        first_parent = {key: min(outside[key], key=position.__getitem__)
                        for key in order if outside[key]}
        needed: set[int] = set()
        for key in order:  # children before parents
            if key in tracked or key in needed:
                needed.add(key)
                if key in first_parent:
                    needed.add(first_parent[key])
        children: dict[int, int] = {}
        for key in needed:
            if key in first_parent:
                children[first_parent[key]] = children.get(first_parent[key], 0) + 1
        visit = [key for key in reversed(order) if key in needed]
        return cls(visit, parents, outside, first_parent, children)


def _sparse_selected_inverse(linear: gtsam.GaussianFactorGraph, tracked_keys: Sequence[int],
                             boundary_keys: Sequence[int]
                             ) -> tuple[FloatArray, FloatArray, FloatArray]:
    """``Sigma_BB`` (|B|, |B|), ``Sigma_ii`` (T, 3, 3) and ``Sigma_iB`` (T, 3, |B|) of the
    tracked poses ``i``, by selected inversion of the whole graph's sparse factorization.

    The graph is eliminated in COLAMD order with the boundary last. Variable j's conditional
    ``R_j x_j + S_j x_Pj = d`` gives, with ``G_j = R_j^-1 S_j`` and any set X of variables
    eliminated after j (Takahashi's recurrence, exact for the linear system)::

        Sigma_jX = -G_j Sigma_Pj,X,      Sigma_jj = R_j^-1 R_j^-T - Sigma_j,Pj G_j^T

    It runs from the last variable to the first (:class:`_EliminationTree`) with
    ``X = U_j + B``, ``U_j`` the parents outside the boundary. In the filled graph ``U_j``
    minus its first-eliminated member u lies in u's own ``U_u``, so ``Sigma`` over
    ``U_j + B`` is a block of the matrix kept for u; each matrix is dropped once its last
    child has used it.
    """
    boundary_set = set(boundary_keys)
    ordering = gtsam.Ordering.ColamdConstrainedLastGaussianFactorGraph(
        linear, gtsam.KeyVector(list(boundary_keys)), True)
    bayes_net = _retry_if_indeterminate(
        lambda: linear.eliminateSequential(ordering),
        lambda: linear.eliminateSequential(ordering, gtsam.EliminateQR))
    conditionals = _conditionals_by_key(bayes_net)
    boundary = _KeyLayout(boundary_keys)
    boundary_covariance = _covariance_of_root(_hub_root(conditionals, boundary))
    boundary_offsets = dict(zip(boundary.keys.tolist(), boundary.offsets.tolist()))
    order = [key for key in (ordering.at(i) for i in range(ordering.size()))
             if key not in boundary_set]
    tracked = set(tracked_keys)
    tree = _EliminationTree.build(order, conditionals, boundary_set, tracked)

    # The loop visits up to a few thousand variables per decision, each with a handful of
    # parents: its index bookkeeping is plain Python (NumPy's per-call cost on arrays of
    # a few elements was most of the loop's time).
    all_keys = order + list(boundary_keys)
    dim_of = dict(zip(all_keys, _key_dims(all_keys).tolist()))
    # kept[u]: (offset of u and of each of U_u in the matrix, Sigma over u, U_u and B)
    kept: dict[int, tuple[dict[int, int], FloatArray]] = {}
    children_left = dict(tree.children)
    marginals: dict[int, FloatArray] = {}
    cross: dict[int, FloatArray] = {}
    for key in tree.visit:
        outside = tree.outside[key]
        offsets: dict[int, int] = {}  # of U_j and B in sigma_x, Sigma over U_j + B
        outside_dim = 0
        for other in outside:
            offsets[other] = outside_dim
            outside_dim += dim_of[other]
        if outside:
            parent = tree.first_parent[key]
            parent_offsets, parent_sigma = kept[parent]
            parent_size = len(parent_sigma)
            rows = np.array(_index_ranges((parent_offsets[other], dim_of[other])
                                          for other in outside)
                            + list(range(parent_size - boundary.dim, parent_size)),
                            dtype=np.int64)
            sigma_x = parent_sigma[rows[:, None], rows]
            children_left[parent] -= 1
            if not children_left[parent]:
                del kept[parent]
        else:
            sigma_x = boundary_covariance
        for other, start in boundary_offsets.items():
            offsets[other] = outside_dim + start
        parent_columns = np.array(_index_ranges((offsets[p], dim_of[p])
                                                for p in tree.parents[key]), dtype=np.int64)
        conditional = conditionals[key]
        inverse_r = np.linalg.inv(conditional.R())
        gain = inverse_r @ conditional.S()
        sigma_jx = -gain @ sigma_x[parent_columns]
        sigma_jj = inverse_r @ inverse_r.T - sigma_jx[:, parent_columns] @ gain.T
        sigma_jj = 0.5 * (sigma_jj + sigma_jj.T)
        if key in tracked:
            marginals[key] = sigma_jj
            cross[key] = sigma_jx[:, outside_dim:]
        if tree.children.get(key):
            size = len(sigma_jj)
            matrix = np.empty((size + len(sigma_x), size + len(sigma_x)))
            matrix[:size, :size] = sigma_jj
            matrix[:size, size:] = sigma_jx
            matrix[size:, :size] = sigma_jx.T
            matrix[size:, size:] = sigma_x
            kept[key] = ({key: 0, **{other: size + offsets[other] for other in outside}},
                         matrix)
    for key in tracked & boundary_set:  # tracked poses that the candidates touch as well
        start = boundary_offsets[key]
        marginals[key] = boundary_covariance[start:start + 3, start:start + 3]
        cross[key] = boundary_covariance[start:start + 3]
    count = len(tracked_keys)
    return (boundary_covariance,
            np.array([marginals[k] for k in tracked_keys]).reshape(count, 3, 3),
            np.array([cross[k] for k in tracked_keys]).reshape(count, 3, boundary.dim))


class DecisionFactorization:
    """Once per decision: the team graph plus the teammates' predicted paths (shared by
    every candidate), linearized at the current estimate and factored once.

    Args:
        snapshot: the team graph, estimate and the deciding robot's history.
        predicted: the candidates' common ``X_predict`` part (``ScenarioBuilder.predicted``).
        boundary_keys: variables the candidates' ``next`` factors may touch (the union of
            the scenarios' ``boundary_keys``).
        with_history: keep alpha's history marginals and cross-covariances (EM's U_M).
        with_predicted: keep those of the predicted waypoints (BSP).
        dense_hub_max_dim: largest hub (dimension) handled densely; above it the covariances
            come from :func:`_sparse_selected_inverse` of the whole graph (the same values to
            round-off, in less time for a large hub).
    """

    def __init__(self, snapshot: TeamSnapshot, predicted: VirtualFactors,
                 boundary_keys: Sequence[int], with_history: bool = True,
                 with_predicted: bool = False,
                 dense_hub_max_dim: int = DENSE_HUB_MAX_DIM) -> None:
        self.predicted_keys = tuple(int(k) for k in predicted.waypoint_keys)
        self.boundary_keys = tuple(int(k) for k in boundary_keys)
        dims = [_key_dim(k) for k in self.boundary_keys]
        self.boundary_offsets = dict(zip(self.boundary_keys,
                                         np.cumsum([0] + dims[:-1]).astype(int).tolist()))
        self.boundary_dim = int(sum(dims))
        self.num_history = len(snapshot.history_keys) if with_history else 0
        tracked = (list(snapshot.history_keys) if with_history else []) + (
            list(self.predicted_keys) if with_predicted else [])
        self.tracked_keys = tuple(tracked)
        graph, values = graph_with_virtual(snapshot, predicted)
        linear = graph.linearize(values)
        reduced = self._marginalize_untracked(linear)
        chain = self._chain_keys(reduced)
        chain_set = set(chain)
        boundary = set(self.boundary_keys)
        hub_keys = sorted(k for k in set(reduced.keyVector())
                          if k not in chain_set and k not in boundary) + list(self.boundary_keys)
        hub = _KeyLayout(hub_keys)
        #: Whether the covariances came from :func:`_sparse_selected_inverse` (a large hub).
        self.sparse = hub.dim > dense_hub_max_dim
        if self.sparse:
            self.boundary_covariance, self.tracked_covariances, self.tracked_cross = \
                _sparse_selected_inverse(linear, self.tracked_keys, self.boundary_keys)
            return
        ordering = gtsam.Ordering()
        for key in chain + hub_keys:
            ordering.push_back(key)
        bayes_net = _retry_if_indeterminate(
            lambda: reduced.eliminateSequential(ordering),
            lambda: reduced.eliminateSequential(ordering, gtsam.EliminateQR))
        conditionals = _conditionals_by_key(bayes_net)
        hub_covariance = _covariance_of_root(_hub_root(conditionals, hub))
        boundary_columns = np.arange(hub.dim - self.boundary_dim, hub.dim)
        #: ``P = Sigma_BB`` (|B|, |B|).
        self.boundary_covariance = hub_covariance[np.ix_(boundary_columns, boundary_columns)]
        chain_marginals, chain_rows = _chain_selected_inverse(chain, conditionals, hub,
                                                              hub_covariance)
        #: ``Sigma_ii`` (T, 3, 3) and ``Sigma_iB`` (T, 3, |B|) of the tracked poses.
        self.tracked_covariances = np.zeros((len(self.tracked_keys), 3, 3))
        self.tracked_cross = np.zeros((len(self.tracked_keys), 3, self.boundary_dim))
        tracked = np.array(self.tracked_keys, dtype=np.int64)
        is_chain = np.isin(tracked, np.array(chain, dtype=np.int64))
        self.tracked_covariances[is_chain] = chain_marginals
        self.tracked_cross[is_chain] = chain_rows[:, :, boundary_columns]
        in_hub = hub.columns(tracked[~is_chain]).reshape(-1, 3)  # tracked keys are poses
        self.tracked_covariances[~is_chain] = hub_covariance[in_hub[:, :, None],
                                                             in_hub[:, None, :]]
        self.tracked_cross[~is_chain] = hub_covariance[in_hub[:, :, None],
                                                       boundary_columns[None, None, :]]

    def _marginalize_untracked(self, linear: gtsam.GaussianFactorGraph
                               ) -> gtsam.GaussianFactorGraph:
        """Eliminate (COLAMD order) every pose that is neither tracked nor in the boundary:
        their conditionals are not needed. Landmarks stay, which keeps the rest sparse."""
        keep = np.array(self.tracked_keys + self.boundary_keys, dtype=np.int64)
        keys = np.fromiter(set(linear.keyVector()), dtype=np.int64)  # set order, as always
        eliminated = keys[(_key_dims(keys) == 3) & ~np.isin(keys, keep)].tolist()
        if not eliminated:
            return linear
        _, remaining = _retry_if_indeterminate(
            lambda: linear.eliminatePartialSequential(eliminated),
            lambda: linear.eliminatePartialSequential(eliminated, gtsam.EliminateQR))
        return remaining

    def _chain_keys(self, reduced: gtsam.GaussianFactorGraph) -> list[int]:
        """The tracked poses, in their order, whose only tracked neighbours in ``reduced``
        are the ones just before and after them, and that are not in the boundary.

        Eliminated first and in this order, each one's conditional has as parents at most
        the next chain pose and variables of the hub (everything else), which is what
        :func:`_chain_selected_inverse` relies on: eliminating pose k - 1 links pose k only
        to pose k and the hub variables pose k - 1 was linked to.
        """
        factors = (reduced.at(index) for index in range(reduced.size()))
        keys = [factor.keys() for factor in factors if factor is not None]
        flat = np.fromiter(itertools.chain.from_iterable(keys), dtype=np.int64)
        owner = np.repeat(np.arange(len(keys)), [len(k) for k in keys])
        place = _KeyLayout(self.tracked_keys).index_of(flat)  # -1: not tracked
        place, owner = place[place >= 0], owner[place >= 0]
        lowest = np.full(len(keys), len(self.tracked_keys), dtype=np.int64)
        highest = np.full(len(keys), -1, dtype=np.int64)
        np.minimum.at(lowest, owner, place)
        np.maximum.at(highest, owner, place)
        spread = (highest - lowest > 1)[owner]
        excluded = set(self.boundary_keys) | {self.tracked_keys[i] for i in place[spread].tolist()}
        return [key for key in self.tracked_keys if key not in excluded]

    def propagate(self, scenario: VirtualScenario) -> PropagationResult:
        """Covariances after adding the scenario's ``next`` measurements (the Woodbury update
        of the module docstring); only the parts requested at construction are filled."""
        return self.propagate_all([scenario])[0]

    def propagate_all(self, scenarios: Sequence[VirtualScenario]) -> list[PropagationResult]:
        """:meth:`propagate` of every scenario; the new waypoints' covariances of all of
        them in one batch (:func:`_chain_covariances`)."""
        updates = [self._update(scenario) for scenario in scenarios]
        waypoints = _chain_covariances(updates)
        return [PropagationResult(update.tracked[:self.num_history],
                                  update.tracked[self.num_history:], blocks)
                for update, blocks in zip(updates, waypoints)]

    def _update(self, scenario: VirtualScenario) -> "_CandidateUpdate":
        """The QR of the scenario's whitened Jacobian (new waypoints first) and the Woodbury
        update of the boundary and the tracked poses."""
        missing = set(scenario.boundary_keys) - set(self.boundary_offsets)
        if missing:
            raise ValueError(f"scenario touches {len(missing)} keys outside the boundary")
        factors = scenario.next
        count = len(factors.waypoint_keys)
        waypoint_dim = 3 * count
        touched = np.concatenate([np.arange(self.boundary_offsets[k],
                                            self.boundary_offsets[k] + _key_dim(k))
                                  for k in scenario.boundary_keys]).astype(int) \
            if scenario.boundary_keys else np.zeros(0, dtype=int)
        local_offsets = np.cumsum([0] + [_key_dim(k) for k in scenario.boundary_keys])
        keys = np.concatenate([factors.waypoint_keys,
                               np.array(scenario.boundary_keys, dtype=np.int64)])
        columns = np.concatenate([3 * np.arange(count), waypoint_dim + local_offsets[:-1]])
        order = np.argsort(keys)

        def columns_of(factor_keys: IntArray) -> IntArray:
            return columns[order][np.searchsorted(keys[order], factor_keys)]

        jacobian = _whitened_jacobian(factors, columns_of, waypoint_dim + len(touched))
        root = np.linalg.qr(jacobian, mode="r")
        update = root[waypoint_dim:, waypoint_dim:].T
        prior = self.boundary_covariance[np.ix_(touched, touched)]
        prior_update = prior @ update
        middle_inverse = np.linalg.inv(np.eye(update.shape[1]) + update.T @ prior_update)
        posterior = prior - prior_update @ middle_inverse @ prior_update.T
        projected = self.tracked_cross[:, :, touched] @ update
        tracked = (self.tracked_covariances
                   - projected @ middle_inverse @ np.swapaxes(projected, 1, 2))
        # R_WW is block upper bidiagonal (the waypoints form a chain; every other factor
        # of a waypoint reaches into B): its diagonal and first off-diagonal 3x3 blocks.
        root_ww = root[:waypoint_dim, :waypoint_dim].reshape(count, 3, count, 3)
        steps = np.arange(count)
        return _CandidateUpdate(tracked, posterior, root_ww[steps, :, steps, :],
                                root_ww[steps[:-1], :, steps[:-1] + 1, :],
                                root[:waypoint_dim, waypoint_dim:].reshape(
                                    count, 3, len(touched)))


@dataclass(frozen=True)
class _CandidateUpdate:
    """One candidate's propagation before its waypoints' covariances: the tracked poses'
    covariances (T, 3, 3), the boundary posterior ``P'`` (t, t) of the t boundary
    dimensions it touches, and the blocks of its square root ``[R_WW R_WB]``: diagonal
    (n, 3, 3), first off-diagonal (n - 1, 3, 3) and ``R_WB`` (n, 3, t)."""

    tracked: FloatArray
    posterior: FloatArray
    diagonal: FloatArray
    off_diagonal: FloatArray
    boundary_rows: FloatArray


def _chain_covariances(updates: Sequence[_CandidateUpdate]) -> list[FloatArray]:
    """The new waypoints' covariances (n, 3, 3) of each update, all updates at once.

    ``x_W = K x_B + e`` with ``K = -R_WW^-1 R_WB`` and ``cov(e) = R_WW^-1 R_WW^-T``; for a
    block upper bidiagonal ``R_WW`` both follow from the last waypoint backwards::

        K_k = R_kk^-1 (-R_kB - R_k,k+1 K_k+1)
        D_k = R_kk^-1 (I + R_k,k+1 D_k+1 R_k,k+1^T) R_kk^-T
        Sigma'_kk = K_k P' K_k^T + D_k

    (``D_k`` the diagonal block of ``cov(e)``: block row k of ``R_WW^-1`` has no entry
    where the identity's row k does). The chains are aligned at their last waypoint and
    padded in front with independent unit blocks, so one step of the recursion serves
    every candidate.
    """
    if not updates:
        return []
    counts = [len(u.diagonal) for u in updates]
    length = max(counts)
    width = max(u.posterior.shape[0] for u in updates)
    diagonal = np.broadcast_to(np.eye(3), (len(updates), length, 3, 3)).copy()
    off_diagonal = np.zeros((len(updates), length, 3, 3))  # block k couples k and k + 1
    boundary_rows = np.zeros((len(updates), length, 3, width))
    posterior = np.zeros((len(updates), width, width))
    for index, (update, count) in enumerate(zip(updates, counts)):
        start, touched = length - count, update.posterior.shape[0]
        diagonal[index, start:] = update.diagonal
        off_diagonal[index, start:length - 1] = update.off_diagonal
        boundary_rows[index, start:, :, :touched] = update.boundary_rows
        posterior[index, :touched, :touched] = update.posterior
    inverse = np.linalg.inv(diagonal)
    inverse_t = np.swapaxes(inverse, -1, -2)
    gains = np.zeros((len(updates), length, 3, width))
    spread = np.zeros((len(updates), length, 3, 3))
    gain, below = np.zeros((len(updates), 3, width)), np.zeros((len(updates), 3, 3))
    for k in range(length - 1, -1, -1):
        coupling = off_diagonal[:, k]
        gain = inverse[:, k] @ (-boundary_rows[:, k] - coupling @ gain)
        below = inverse[:, k] @ (np.eye(3) + coupling @ below @ np.swapaxes(coupling, 1, 2)) \
            @ inverse_t[:, k]
        gains[:, k], spread[:, k] = gain, below
    blocks = (gains @ posterior[:, None] @ np.swapaxes(gains, -1, -2)) + spread
    return [blocks[index, length - count:] for index, count in enumerate(counts)]
