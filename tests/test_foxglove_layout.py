"""config/foxglove_layout.json opens useful panels on a recording of a team: every panel of
its tree is configured, and every topic, message field and frame it names is in the sample
recording (bags/sample_3robots, a 3-robot run)."""
from __future__ import annotations

import json
from pathlib import Path

from tf_chains import recorded_transforms

from em_exploration_ros.bag_format.bag_reader import scan_bag
from em_exploration_ros.tools.bag_ros import import_message_class

REPO = Path(__file__).resolve().parents[1]
LAYOUT = json.loads((REPO / "config" / "foxglove_layout.json").read_text())
SAMPLE = REPO / "bags" / "sample_3robots"


def _panel_ids(node: str | dict) -> list[str]:
    if isinstance(node, str):
        return [node]
    return _panel_ids(node["first"]) + _panel_ids(node["second"])


def test_every_panel_of_the_layout_is_configured() -> None:
    assert sorted(_panel_ids(LAYOUT["layout"])) == sorted(LAYOUT["configById"])
    assert {panel.split("!")[0] for panel in LAYOUT["configById"]} == {
        "3D", "Plot", "RawMessages", "TransformTree"}


def test_layout_names_only_what_a_recording_holds() -> None:
    info = scan_bag(SAMPLE)
    types = {channel.topic: info.schema_of(channel).name for channel in info.channels.values()}
    panels = LAYOUT["configById"]
    scene = panels["3D!team"]
    assert set(scene["topics"]) <= set(types)
    assert panels["RawMessages!metrics"]["topicPath"] in types
    for series in panels["Plot!metrics"]["paths"]:
        topic, field = series["value"].split(".", 1)
        assert field in import_message_class(types[topic]).get_fields_and_field_types(), field
    tf, static = recorded_transforms(SAMPLE)
    frames = {frame for edges in (tf, static) for edge in edges for frame in edge}
    assert scene["followTf"] in frames
    assert {key.removeprefix("frame:") for key in scene["transforms"]} <= frames
    assert scene["layers"]["grid"]["frameId"] in frames
