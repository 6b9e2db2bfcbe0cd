"""Planner plugins: planners are found by name in the entry-point group
``em_exploration_ros.planners`` (core/planner_registry.py), the built-in ones included.

The example plugin (examples/spread_planner, docs/plugins.md) is installed with
``pip install --target`` into a temporary folder and selected with ``--planner SPREAD`` in
em-sim, em-bench and run_team.sh (EM_PLUGIN_PATH); the ROS team in lockstep chooses the same
targets as em-sim, on a world file. An unknown name is refused with the installed ones.
"""
from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
from ros_process import (REPO_ROOT, RUN_PROCESS_PATTERN, RUN_TEAM, finish_team_run,
                         processes_in_domain, start_team_run)

from em_exploration_ros.core.params import ExplorationParams
from em_exploration_ros.core.planner_registry import (BUILT_IN_PLANNERS, PLANNER_GROUP,
                                                      installed_planner_names,
                                                      planner_entry_points)
from em_exploration_ros.core.planning import planners
from em_exploration_ros.core.planning.planners import make_planner

VENV_BIN = Path(sys.executable).parent
EXAMPLE = REPO_ROOT / "examples" / "spread_planner"
INSTALLED = "EM_2 EM_3 CE BSP NEAREST SPREAD"
#: Bound of the ROS team's run (start-up, exploration, shutdown) [s].
RUN_TIMEOUT_S = 150.0

WORLD = """width_m: 40.0
height_m: 40.0
landmarks:  # x [m], y [m], radius [m]
  - [20.0, 20.0, 1.0]
  - [30.0, 10.0, 1.0]
  - [12.0, 32.0, 1.0]
starts:  # x [m], y [m], yaw [rad]
  - [5.0, 20.0, 0.0]
  - [5.0, 23.0, 1.0]
"""


@pytest.fixture(scope="module")
def plugin_site(tmp_path_factory) -> Path:
    """The example plugin installed with pip into a folder of its own (from a copy: a build
    writes into its source folder)."""
    root = tmp_path_factory.mktemp("plugin")
    shutil.copytree(EXAMPLE, root / "src")
    subprocess.run([sys.executable, "-m", "pip", "install", "--quiet", "--no-deps",
                    "--no-build-isolation", "--no-index", "--target", str(root / "site"),
                    str(root / "src")], check=True, capture_output=True, timeout=300)
    return root / "site"


def _with_path(site: Path) -> dict[str, str]:
    return {**os.environ, "PYTHONPATH": str(site)}


def test_the_built_in_planners_register_through_the_group():
    entry_points = planner_entry_points()
    assert tuple(entry_points)[:5] == BUILT_IN_PLANNERS
    assert {entry.group for entry in entry_points.values()} == {PLANNER_GROUP}
    params = ExplorationParams()
    kinds = {"EM_2": planners.EmPlanner, "EM_3": planners.EmPlanner,
             "CE": planners.CoordinatedPlanner, "BSP": planners.BspPlanner,
             "NEAREST": planners.NearestFrontierPlanner}
    for name, kind in kinds.items():
        assert entry_points[name].value.startswith("em_exploration_ros.core.planning.planners:")
        planner = make_planner(params, name)
        assert type(planner) is kind and planner.name == name


def test_a_plugin_is_found_selected_and_checked(plugin_site, monkeypatch):
    assert "SPREAD" not in installed_planner_names()
    with pytest.raises(ValueError, match="must be one of"):
        ExplorationParams().replace(planner={"name": "SPREAD"})
    monkeypatch.syspath_prepend(str(plugin_site))
    assert installed_planner_names() == tuple(INSTALLED.split())
    params = ExplorationParams().replace(planner={"name": "SPREAD"})
    planner = make_planner(params)
    assert planner.name == "SPREAD" and type(planner).__module__ == "spread_planner"
    with pytest.raises(ValueError, match="unknown planner 'XYZ'; installed: EM_2, EM_3, CE, "
                                         "BSP, NEAREST, SPREAD"):
        make_planner(params, "XYZ")
    with pytest.raises(ValueError, match=r"must be one of \('EM_2', 'EM_3', 'CE', 'BSP', "
                                         r"'NEAREST', 'SPREAD'\), got 'XYZ'"):
        params.replace(planner={"name": "XYZ"})


def test_a_plugin_that_cannot_be_loaded_is_named(tmp_path, monkeypatch):
    info = tmp_path / "broken_planner-1.0.dist-info"
    info.mkdir()
    (info / "METADATA").write_text("Metadata-Version: 2.1\nName: broken-planner\nVersion: 1.0\n")
    (info / "entry_points.txt").write_text(f"[{PLANNER_GROUP}]\nBROKEN = absent_module:Planner\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    assert installed_planner_names()[-1] == "BROKEN"
    params = ExplorationParams().replace(planner={"name": "BROKEN"})
    with pytest.raises(ValueError, match="planner 'BROKEN': cannot load absent_module:Planner "
                                         r"\(ModuleNotFoundError: No module named"):
        make_planner(params)


def test_em_sim_refuses_an_unknown_planner_with_the_installed_ones(plugin_site):
    result = subprocess.run([str(VENV_BIN / "em-sim"), "--planner", "XYZ"], capture_output=True,
                            text=True, timeout=120, env=_with_path(plugin_site))
    assert result.returncode == 2
    assert ("argument --planner: invalid choice: 'XYZ' (choose from 'EM_2', 'EM_3', 'CE', "
            "'BSP', 'NEAREST', 'SPREAD')") in result.stderr


def test_run_team_refuses_an_unknown_planner_with_the_installed_ones(plugin_site, monkeypatch):
    monkeypatch.setenv("EM_PLUGIN_PATH", str(plugin_site))
    result = subprocess.run(["bash", str(RUN_TEAM), "--planner", "XYZ"], capture_output=True,
                            text=True, timeout=60, stdin=subprocess.DEVNULL)
    assert result.returncode == 2, result.stderr
    assert f"run_team.sh: error: unknown planner 'XYZ' (installed: {INSTALLED})" in result.stderr
    assert "--help" in result.stderr and "logs in" not in result.stdout


def test_em_bench_runs_a_plugin(plugin_site, tmp_path):
    world = tmp_path / "world.yaml"
    world.write_text(WORLD)
    out = tmp_path / "bench"
    result = subprocess.run([str(VENV_BIN / "em-bench"), "planners", "--world", str(world),
                             "--planners", "SPREAD", "NEAREST", "--trials", "1",
                             "--until-explored", "0.5", "--jobs", "1", "--out", str(out)],
                            capture_output=True, text=True, timeout=300,
                            env=_with_path(plugin_site))
    assert result.returncode == 0, result.stderr[-2000:]
    summary = json.loads((out / "summary.json").read_text())
    setting = next(iter(summary["settings"].values()))
    assert list(setting["planners"]) == ["NEAREST", "SPREAD"]  # the installed order
    assert setting["planners"]["SPREAD"]["trials_done"] == 1


def test_the_ros_team_chooses_the_targets_em_sim_chooses_with_a_plugin(plugin_site, tmp_path,
                                                                        monkeypatch):
    world = tmp_path / "world.yaml"
    world.write_text(WORLD)
    common = ["--world", str(world), "--planner", "SPREAD", "--seed", "1",
              "--until-explored", "0.7"]
    reference_path = tmp_path / "em_sim.json"
    result = subprocess.run([str(VENV_BIN / "em-sim"), *common, "--max-steps", "1500",
                             "--quiet", "--summary", str(reference_path)],
                            capture_output=True, text=True, timeout=300,
                            env=_with_path(plugin_site))
    assert result.returncode == 0, result.stderr[-2000:]
    reference = json.loads(reference_path.read_text())
    assert reference["planner"] == "SPREAD" and reference["num_robots"] == 2

    monkeypatch.setenv("EM_PLUGIN_PATH", str(plugin_site))
    summary_path = tmp_path / "run" / "summary.json"
    run, domain = start_team_run(tmp_path, *common, "--robots", "2", "--max-sim-time", "300",
                                 "--summary", str(summary_path))
    code = finish_team_run(run, RUN_TIMEOUT_S)
    assert code == 0, run.output()[-3000:]
    summary = json.loads(summary_path.read_text())
    assert summary["planner"] == "SPREAD" and summary["num_robots"] == 2
    assert [r["targets"] for r in summary["robots"]] == [r["targets"] for r in
                                                         reference["robots"]]
    assert (summary["stop_reason"], summary["sim_time_s"]) == (reference["stop_reason"],
                                                               reference["sim_time_s"])
    assert processes_in_domain(RUN_PROCESS_PATTERN, domain) == []
