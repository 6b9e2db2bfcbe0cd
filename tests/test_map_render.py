"""The final-map PNG: a real image whose pixels show the layers where they belong."""
from __future__ import annotations

import numpy as np
import pytest
from matplotlib.image import imread

import dataclasses

from em_exploration_ros.core.evaluation.map_layers import TeamMapLayers
from em_exploration_ros.core.evaluation.map_render import EXPLORED_RGBA, render_team_map
from em_exploration_ros.core.evaluation.rendezvous_stats import RendezvousOutcome
from em_exploration_ros.core.evaluation.summary import TargetEntry


def layers(explored: np.ndarray) -> TeamMapLayers:
    t = np.linspace(0.0, 1.0, 20)
    path = np.column_stack([5 + 10 * t, 20 + 5 * t, np.zeros_like(t)])
    return TeamMapLayers(
        width_m=40.0, height_m=40.0, cell_size_m=2.0, explored=explored,
        true_landmarks=np.array([[30.0, 30.0], [10.0, 35.0]]), landmark_radius_m=1.0,
        true_paths={0: path, 1: path + [0.0, 3.0, 0.0]},
        estimated_paths={0: path + 0.3, 1: path + [0.3, 3.3, 0.0]},
        estimated_landmarks={0: np.array([[30.2, 29.9]]), 1: np.zeros((0, 2))},
        targets={0: [TargetEntry(15.0, 25.0, "exploration"), TargetEntry(30.0, 27.0, "revisiting")],
                 1: [TargetEntry(12.0, 30.0, "rendezvous")]},
        title="test")


def colour_fraction(image: np.ndarray, rgba: tuple[float, ...]) -> float:
    return float(np.mean(np.all(np.abs(image[..., :3] - np.array(rgba[:3])) < 0.02, axis=-1)))


def test_png_written_and_explored_area_drawn(tmp_path):
    none = np.zeros((20, 20), dtype=bool)
    half = none.copy()
    half[:, :10] = True  # the west half, x < 20 m
    empty = imread(render_team_map(layers(none), tmp_path / "a" / "empty.png"))
    shaded = imread(render_team_map(layers(half), tmp_path / "half.png"))
    assert empty.shape == shaded.shape and empty.shape[0] > 300 and empty.shape[1] > 300
    assert colour_fraction(empty, EXPLORED_RGBA) < 0.001
    # The west half of a 40 m map is a fifth of the picture or more (the legend takes the rest).
    assert colour_fraction(shaded, EXPLORED_RGBA) > 0.1


def test_rejects_a_mask_that_is_not_2d(tmp_path):
    with pytest.raises(ValueError, match="2-D"):
        render_team_map(layers(np.zeros(400, dtype=bool)), tmp_path / "x.png")


def test_rendezvous_rings_are_drawn(tmp_path):
    explored = np.zeros((20, 20), dtype=bool)
    plain = imread(render_team_map(layers(explored), tmp_path / "plain.png"))
    met = RendezvousOutcome(0, 1, 2, 10.0, 20.0, 12.0, "met")
    missed = RendezvousOutcome(1, 0, 5, 30.0, 8.0, 30.0, "timed_out")
    marked = imread(render_team_map(dataclasses.replace(layers(explored), rendezvous=(met, missed)),
                                    tmp_path / "marked.png"))
    black = colour_fraction(marked, (0.0, 0.0, 0.0)) - colour_fraction(plain, (0.0, 0.0, 0.0))
    grey = colour_fraction(marked, (0.5, 0.5, 0.5)) - colour_fraction(plain, (0.5, 0.5, 0.5))
    assert black > 0.0002 and grey > 0.0002  # two rings of ~18 pt, one each
