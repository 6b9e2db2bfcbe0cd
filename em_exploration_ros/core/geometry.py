"""SE(2) helpers, vectorized over leading dimensions.

A pose is ``(x [m], y [m], theta [rad])`` of a body frame expressed in a parent frame,
with theta wrapped to (-pi, pi]. Arrays of poses have shape ``(..., 3)`` and arrays of
points ``(..., 2)``; leading dimensions broadcast with NumPy rules. Jacobians and
covariances are taken with respect to the pose coordinates ``(x, y, theta)`` (additive
perturbations), in that order.
"""
from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike, NDArray

FloatArray = NDArray[np.float64]

_TWO_PI = 2.0 * np.pi


def wrap_angle(angle: ArrayLike) -> FloatArray:
    """Angles [rad] wrapped to (-pi, pi], same shape as the input.

    A single float (Python or NumPy) takes a scalar path: the same IEEE operations, so the
    same result to the last bit, at a tenth of the array path's overhead (the simulation
    and the agents wrap single angles hundreds of thousands of times per run).
    """
    if isinstance(angle, float):
        return np.float64(_wrap_float(angle))
    angle = np.asarray(angle, dtype=float)
    wrapped = angle - _TWO_PI * np.ceil((angle - np.pi) / _TWO_PI)
    return np.where(wrapped <= -np.pi, wrapped + _TWO_PI, wrapped)


def _wrap_float(angle: float) -> float:
    """:func:`wrap_angle` of one Python float, as a Python float (NaN if not finite)."""
    if not math.isfinite(angle):
        return math.nan
    wrapped = angle - _TWO_PI * math.ceil((angle - math.pi) / _TWO_PI)
    return wrapped + _TWO_PI if wrapped <= -math.pi else wrapped


def _is_single(*arrays: FloatArray) -> bool:
    """Whether every array is one vector (a single pose or point), not a batch.

    The single-pose paths below evaluate the batch formulas in Python floats: the same
    IEEE operations in the same order, so the same result to the last bit (``math.cos``
    and ``math.sin`` round like NumPy's on the supported platforms; the geometry tests
    compare both paths), at a fraction of the overhead of NumPy calls on 3-element
    arrays. The simulation and the agents call these functions tens of thousands of
    times per run with single poses.
    """
    return all(array.ndim == 1 for array in arrays)


def _cos_sin(angle: float) -> tuple[float, float]:
    """Cosine and sine of one angle [rad]; NaN for an infinite angle, as NumPy gives."""
    if math.isinf(angle):
        return math.nan, math.nan
    return math.cos(angle), math.sin(angle)


def read_only_point(value: ArrayLike) -> FloatArray:
    """A read-only float copy (2,) of a 2-D point [m]."""
    point = np.array(value, dtype=float).reshape(2)
    point.flags.writeable = False
    return point


def _rotate(cos_t: FloatArray, sin_t: FloatArray, x: FloatArray,
            y: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Rotate the vector (x, y) by the angle whose cosine and sine are given."""
    return cos_t * x - sin_t * y, sin_t * x + cos_t * y


def compose(a: ArrayLike, b: ArrayLike) -> FloatArray:
    """``a ⊕ b``: pose ``b`` (given in frame ``a``) expressed in ``a``'s parent frame."""
    a = np.asarray(a, dtype=float)
    b = np.asarray(b, dtype=float)
    if _is_single(a, b):
        (ax, ay, at), (bx, by, bt) = a.tolist(), b.tolist()
        cos_t, sin_t = _cos_sin(at)
        return np.array([ax + (cos_t * bx - sin_t * by), ay + (sin_t * bx + cos_t * by),
                         _wrap_float(at + bt)])
    cos_t, sin_t = np.cos(a[..., 2]), np.sin(a[..., 2])
    x, y = _rotate(cos_t, sin_t, b[..., 0], b[..., 1])
    return np.stack([a[..., 0] + x, a[..., 1] + y, wrap_angle(a[..., 2] + b[..., 2])], axis=-1)


def inverse(pose: ArrayLike) -> FloatArray:
    """``pose^-1``: the parent frame expressed in the pose's body frame."""
    pose = np.asarray(pose, dtype=float)
    cos_t, sin_t = np.cos(pose[..., 2]), np.sin(pose[..., 2])
    x, y = _rotate(cos_t, -sin_t, -pose[..., 0], -pose[..., 1])
    return np.stack([x, y, wrap_angle(-pose[..., 2])], axis=-1)


def between(a: ArrayLike, b: ArrayLike) -> FloatArray:
    """``a^-1 ⊕ b``: pose ``b`` expressed in the body frame of pose ``a``."""
    a = np.asarray(a, dtype=float)
    b = np.asarray(b, dtype=float)
    if _is_single(a, b):
        (ax, ay, at), (bx, by, bt) = a.tolist(), b.tolist()
        cos_t, sin_t = _cos_sin(at)
        neg_sin, dx, dy = -sin_t, bx - ax, by - ay  # as _rotate(cos_t, -sin_t, dx, dy)
        return np.array([cos_t * dx - neg_sin * dy, neg_sin * dx + cos_t * dy,
                         _wrap_float(bt - at)])
    xy = inverse_transform_points(a, b[..., :2])
    return np.concatenate([xy, wrap_angle(b[..., 2] - a[..., 2])[..., None]], axis=-1)


def transform_points(pose: ArrayLike, points: ArrayLike) -> FloatArray:
    """Points ``(..., 2)`` [m] from the pose's body frame to its parent frame.

    A single pose ``(3,)`` applies to every point of ``(N, 2)``; poses ``(N, 3)`` pair
    element-wise with points ``(N, 2)``.
    """
    pose = np.asarray(pose, dtype=float)
    points = np.asarray(points, dtype=float)
    cos_t, sin_t = np.cos(pose[..., 2]), np.sin(pose[..., 2])
    x, y = _rotate(cos_t, sin_t, points[..., 0], points[..., 1])
    return np.stack([pose[..., 0] + x, pose[..., 1] + y], axis=-1)


def inverse_transform_points(pose: ArrayLike, points: ArrayLike) -> FloatArray:
    """Points ``(..., 2)`` [m] from the pose's parent frame to its body frame."""
    pose = np.asarray(pose, dtype=float)
    points = np.asarray(points, dtype=float)
    cos_t, sin_t = np.cos(pose[..., 2]), np.sin(pose[..., 2])
    x, y = _rotate(cos_t, -sin_t, points[..., 0] - pose[..., 0], points[..., 1] - pose[..., 1])
    return np.stack([x, y], axis=-1)


def range_bearing(pose: ArrayLike, points: ArrayLike) -> tuple[FloatArray, FloatArray]:
    """Range [m] and bearing [rad] of points ``(..., 2)`` seen from poses ``(..., 3)``.

    Both are in the parent frame of the pose on input; the bearing is measured in the
    pose's body frame (counter-clockwise from its x axis), wrapped to (-pi, pi].
    """
    pose = np.asarray(pose, dtype=float)
    points = np.asarray(points, dtype=float)
    dx = points[..., 0] - pose[..., 0]
    dy = points[..., 1] - pose[..., 1]
    return np.hypot(dx, dy), wrap_angle(np.arctan2(dy, dx) - pose[..., 2])


def compose_jacobians(a: ArrayLike, b: ArrayLike) -> tuple[FloatArray, FloatArray]:
    """Jacobians ``(..., 3, 3)`` of ``compose(a, b)`` w.r.t. the coordinates of ``a`` and ``b``.

    First-order covariance propagation of independent pose errors:
    ``cov(a ⊕ b) = J_a cov(a) J_a^T + J_b cov(b) J_b^T``.
    """
    a = np.asarray(a, dtype=float)
    b = np.asarray(b, dtype=float)
    if _is_single(a, b):
        at, (bx, by, _) = float(a[2]), b.tolist()
        cos_t, sin_t = _cos_sin(at)
        return (np.array([[1.0, 0.0, -sin_t * bx - cos_t * by],
                          [0.0, 1.0, cos_t * bx - sin_t * by],
                          [0.0, 0.0, 1.0]]),
                np.array([[cos_t, -sin_t, 0.0], [sin_t, cos_t, 0.0], [0.0, 0.0, 1.0]]))
    shape = np.broadcast_shapes(a.shape[:-1], b.shape[:-1])
    cos_t, sin_t = np.cos(a[..., 2]), np.sin(a[..., 2])
    bx, by = b[..., 0], b[..., 1]
    j_a = np.broadcast_to(np.eye(3), shape + (3, 3)).copy()
    j_a[..., 0, 2] = -sin_t * bx - cos_t * by
    j_a[..., 1, 2] = cos_t * bx - sin_t * by
    j_b = np.broadcast_to(np.eye(3), shape + (3, 3)).copy()
    j_b[..., 0, 0] = cos_t
    j_b[..., 0, 1] = -sin_t
    j_b[..., 1, 0] = sin_t
    j_b[..., 1, 1] = cos_t
    return j_a, j_b


def inverse_jacobian(pose: ArrayLike) -> FloatArray:
    """Jacobian ``(3, 3)`` of ``inverse(pose)`` w.r.t. the coordinates of ``pose`` ``(3,)``:
    ``cov(inverse(p)) = J cov(p) J^T``."""
    x, y, theta = (float(value) for value in np.asarray(pose, dtype=float))
    cos_t, sin_t = _cos_sin(theta)
    return np.array([[-cos_t, -sin_t, sin_t * x - cos_t * y],
                     [sin_t, -cos_t, cos_t * x + sin_t * y],
                     [0.0, 0.0, -1.0]])


def coordinate_to_body_covariance(pose: ArrayLike, covariance: ArrayLike) -> FloatArray:
    """Covariance ``(..., 3, 3)`` of additive coordinate errors of ``pose``, re-expressed
    in the pose's own body frame (first order): position rotated by ``-theta``, heading kept.

    This is the frame of a GTSAM ``Pose2`` tangent vector (``x``, ``y`` in the body frame),
    e.g. for the noise model of a between factor whose measurement is ``pose``.
    """
    pose = np.asarray(pose, dtype=float)
    covariance = np.asarray(covariance, dtype=float)
    cos_t, sin_t = np.cos(pose[..., 2]), np.sin(pose[..., 2])
    rotation = np.broadcast_to(np.eye(3), pose.shape[:-1] + (3, 3)).copy()
    rotation[..., 0, 0] = cos_t
    rotation[..., 0, 1] = sin_t
    rotation[..., 1, 0] = -sin_t
    rotation[..., 1, 1] = cos_t
    return rotation @ covariance @ np.swapaxes(rotation, -1, -2)
