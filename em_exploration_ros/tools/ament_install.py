"""Lay out em_exploration_ros in a prefix as colcon installs an ament_python package.

launch_scripts/setup_env.sh runs it after the editable pip install, with the venv as prefix:

- ``share/ament_index/resource_index/packages/em_exploration_ros``: the ament index marker
  (``ament_index_python.get_package_prefix`` and ``ros2 pkg`` find the package by it);
- ``share/em_exploration_ros/package.xml``, ``share/em_exploration_ros/config/*`` and
  ``config/worlds/*`` (the shipped world files);
- ``lib/em_exploration_ros/<name>``: one executable per console script of the project, a
  small shell launcher that runs the console script's function with the venv's Python in
  the venv's own ROS 2 environment (what launch_scripts/_common.sh ``em_activate`` exports,
  the team's Fast DDS profile included),
  so it works from a shell that sourced a full ROS 2 install (whose PYTHONPATH and libraries
  belong to another Python). ``ros2 run em_exploration_ros <name>`` looks for executables
  exactly there (``<prefix>/lib/<package>/``); the console scripts in ``bin/`` stay.

Every file it writes is listed in a manifest; the next run removes the listed files first,
so a renamed executable or config file does not linger. Stdout: one line per file written.

    python -m em_exploration_ros.tools.ament_install --prefix PREFIX --manifest FILE
"""
from __future__ import annotations

import importlib.metadata
import re
import shlex
import shutil
import sys
from pathlib import Path

from em_exploration_ros.tools.cli_parser import CliParser

PACKAGE = "em_exploration_ros"
REPO_ROOT = Path(__file__).resolve().parents[2]


def _normalized(distribution_name: str) -> str:
    """A distribution name as PEP 503 compares them (``em-exploration-ros``)."""
    return re.sub(r"[-_.]+", "-", distribution_name).lower()


def console_scripts() -> dict[str, str]:
    """``{name: "module:function"}`` of the installed project's console scripts."""
    return {entry.name: entry.value
            for entry in importlib.metadata.entry_points(group="console_scripts")
            if entry.dist is not None and _normalized(entry.dist.name) == _normalized(PACKAGE)}


def launcher_text(prefix: Path, python: Path, target: str) -> str:
    """A shell launcher that runs ``module:function`` with ``python`` (in the venv
    ``prefix``) and the arguments it was given, exiting with the function's return value."""
    module, function = target.split(":")
    code = f"import sys; from {module} import {function}; sys.exit({function}())"
    venv = shlex.quote(str(prefix))
    profiles = shlex.quote(str(prefix / "share" / PACKAGE / "config" / "fastdds_profiles.xml"))
    return ("#!/bin/sh\n"
            f"# em_exploration_ros executable: {module}:{function} with the venv's Python in\n"
            "# the venv's ROS 2 environment (written by em_exploration_ros.tools.ament_install).\n"
            f"export VIRTUAL_ENV={venv} AMENT_PREFIX_PATH={venv} CMAKE_PREFIX_PATH={venv}\n"
            f"export PATH={venv}/bin:\"$PATH\" RMW_IMPLEMENTATION=rmw_fastrtps_cpp "
            "ROS_DISTRO=jazzy\n"
            "# the team's Fast DDS profile (config/fastdds_profiles.xml) unless one is chosen\n"
            "[ -n \"$FASTRTPS_DEFAULT_PROFILES_FILE\" ] || "
            f"FASTRTPS_DEFAULT_PROFILES_FILE={profiles}\n"
            "export FASTRTPS_DEFAULT_PROFILES_FILE\n"
            "# its memory policy taken, and freed memory given back (launch_scripts/_common.sh)\n"
            ": \"${RMW_FASTRTPS_USE_QOS_FROM_XML:=1}\" \"${MALLOC_ARENA_MAX:=2}\" "
            "\"${MALLOC_MMAP_THRESHOLD_:=131072}\" \"${MALLOC_TRIM_THRESHOLD_:=131072}\"\n"
            "export RMW_FASTRTPS_USE_QOS_FROM_XML MALLOC_ARENA_MAX MALLOC_MMAP_THRESHOLD_ "
            "MALLOC_TRIM_THRESHOLD_\n"
            "unset PYTHONPATH PYTHONHOME LD_LIBRARY_PATH COLCON_PREFIX_PATH "
            "_ROS_WHEELS_BOOTSTRAP_COMPLETE\n"
            f"exec {shlex.quote(str(python))} -c {shlex.quote(code)} \"$@\"\n")


def _uninstall(manifest: Path) -> None:
    if manifest.is_file():
        for line in manifest.read_text(encoding="utf-8").splitlines():
            Path(line).unlink(missing_ok=True)
        manifest.unlink()


def install(prefix: Path, manifest: Path, python: Path, repo: Path = REPO_ROOT) -> list[Path]:
    """Install the layout described in the module docstring into ``prefix``; returns the
    files written (also written to ``manifest``)."""
    _uninstall(manifest)
    written: list[Path] = []

    def copy(source: Path, target: Path) -> None:
        target.parent.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(source, target)
        written.append(target)

    share = prefix / "share"
    index = share / "ament_index" / "resource_index" / "packages"
    copy(repo / "resource" / PACKAGE, index / PACKAGE)
    copy(repo / "package.xml", share / PACKAGE / "package.xml")
    configs = sorted((repo / "config").glob("*")) + sorted((repo / "config").glob("worlds/*"))
    for config in configs:
        if config.is_file():
            copy(config, share / PACKAGE / config.relative_to(repo))
    executables = prefix / "lib" / PACKAGE
    executables.mkdir(parents=True, exist_ok=True)
    for name, target in sorted(console_scripts().items()):
        path = executables / name
        path.write_text(launcher_text(prefix, python, target), encoding="utf-8")
        path.chmod(0o755)
        written.append(path)
    manifest.parent.mkdir(parents=True, exist_ok=True)
    manifest.write_text("".join(f"{path}\n" for path in written), encoding="utf-8")
    return written


def main(argv: list[str] | None = None) -> int:
    """Entry point; returns the exit code (1 if the project is not installed in this Python)."""
    parser = CliParser(prog="ament_install", description=__doc__.splitlines()[0])
    parser.add_argument("--prefix", type=Path, required=True, help="install prefix (the venv)")
    parser.add_argument("--manifest", type=Path, required=True,
                        help="file listing what was installed (read, then rewritten)")
    args = parser.parse_args(argv)
    if not console_scripts():
        sys.stderr.write(f"ament_install: {PACKAGE} is not installed in {sys.prefix} "
                         "(pip install -e . first)\n")
        return 1
    for path in install(args.prefix.resolve(), args.manifest, Path(sys.executable)):
        sys.stdout.write(f"{path}\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
