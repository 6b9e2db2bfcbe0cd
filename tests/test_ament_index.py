"""The venv's ament index registers em_exploration_msgs as a full ROS 2 install expects it.

`ros2 interface show em_exploration_msgs/msg/<Type>` and `ros2 topic echo` resolve a type
through the 'rosidl_interfaces' resource and read share/em_exploration_msgs/msg/<Type>.msg;
these tests check both against the .msg files of the working tree.
"""
from __future__ import annotations

import sys
from pathlib import Path

from ament_index_python import get_resource, get_resources
from ament_index_python.packages import get_package_share_directory
from catkin_pkg.package import parse_package

from msg_samples import MSG_DIR, PACKAGE, message_type_names


def test_rosidl_interfaces_resource_lists_every_message() -> None:
    """The 'rosidl_interfaces' resource lists msg/<Type>.msg and .idl for every .msg file."""
    content, prefix = get_resource("rosidl_interfaces", PACKAGE)
    assert Path(prefix) == Path(sys.prefix)
    entries = set(content.splitlines())
    names = message_type_names()
    assert {e for e in entries if e.endswith(".msg")} == {f"msg/{n}.msg" for n in names}
    assert {f"msg/{n}.idl" for n in names} <= entries


def test_package_is_registered() -> None:
    """em_exploration_msgs is an ament package of the venv with a valid format-3 manifest."""
    assert PACKAGE in get_resources("packages")
    manifest = parse_package(get_package_share_directory(PACKAGE))
    manifest.validate()
    assert manifest.package_format == 3
    assert "rosidl_interface_packages" in [group.name for group in manifest.member_of_groups]


def test_share_holds_current_msg_files() -> None:
    """share/em_exploration_msgs/msg/ holds exactly the working tree's .msg files."""
    share_msg_dir = Path(get_package_share_directory(PACKAGE)) / "msg"
    installed = {p.name: p.read_bytes() for p in share_msg_dir.glob("*.msg")}
    source = {p.name: p.read_bytes() for p in MSG_DIR.glob("*.msg")}
    assert installed.keys() == source.keys()
    stale = sorted(name for name in source if installed[name] != source[name])
    assert not stale, f"installed .msg files differ from msg_schemas/msg (rerun setup): {stale}"
