"""Uncertainty ellipses of 2-D covariances (the virtual map's cells, as in the paper's figures):
what the robots' markers and the team map picture both draw."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: Ellipses are stored at this many standard deviations (as the robots' markers).
ELLIPSE_SIGMAS = 3.0


@dataclass(frozen=True)
class UncertaintyEllipses:
    """Virtual-map cell uncertainty ellipses: ``centres`` (K, 2) [m]; ``axes`` (K, 2) full
    lengths (major, minor) [m] at ``ELLIPSE_SIGMAS`` standard deviations; ``angles`` (K,)
    [rad] of the major axis from map x."""

    centres: np.ndarray
    axes: np.ndarray
    angles: np.ndarray

    @property
    def count(self) -> int:
        """Number of ellipses."""
        return len(self.centres)


def covariance_ellipses(centres: np.ndarray, covariances: np.ndarray) -> UncertaintyEllipses:
    """Ellipses of 2x2 covariances ``(K, 2, 2)`` [m^2] centred at ``centres`` (K, 2) [m],
    at ``ELLIPSE_SIGMAS``."""
    covariances = np.asarray(covariances, dtype=float).reshape(-1, 2, 2)
    eigenvalues, eigenvectors = np.linalg.eigh(covariances)
    axes = ELLIPSE_SIGMAS * 2.0 * np.sqrt(np.clip(eigenvalues[:, ::-1], 0.0, None))
    angles = np.arctan2(eigenvectors[:, 1, 1], eigenvectors[:, 0, 1])
    return UncertaintyEllipses(np.asarray(centres, dtype=float).reshape(-1, 2), axes, angles)
