"""World files (core/world/world_file.py): a saved world runs as the seeded run it came from;
the shipped worlds are the seeded ones; every malformed, inconsistent or hostile file is
refused before anything starts, with one line naming the problem and exit code 2 (em-sim,
em-bench, run_team.sh), and a world node given a file that does not match its parameters
does not start."""
from __future__ import annotations

import json
import os
import subprocess
from pathlib import Path

import numpy as np
import pytest
from ros_process import REPO_ROOT, RUN_TEAM

from em_exploration_ros.core.params import ExplorationParams
from em_exploration_ros.core.world.simulation import WorldSimulation
from em_exploration_ros.core.world.world import generate_world, run_seed_sequences
from em_exploration_ros.core.world.world_file import (MAX_FILE_BYTES, WorldFileError,
                                                      params_for_world, read_world_file,
                                                      world_for_params, world_yaml)
from em_exploration_ros.tools import bench, sim_cli

SMALL = ["--quiet", "--robots", "2", "--map-size", "40", "--landmarks", "4", "--seed", "5",
         "--planner", "NEAREST", "--max-steps", "300"]
WORLDS = REPO_ROOT / "config" / "worlds"

#: A valid small world: 40 m x 30 m, two landmarks, two robots 3 m apart.
GOOD = {"width_m": 40.0, "height_m": 30.0,
        "landmarks": [[20.0, 15.0, 1.0], [30.0, 5.0, 1.0]],
        "starts": [[5.0, 15.0, 0.0], [5.0, 18.0, 3.0]]}


def _without_wall_times(value):
    """A summary without what the wall clock measures (wall_s, decision times)."""
    if isinstance(value, dict):
        return {key: _without_wall_times(item) for key, item in value.items()
                if "wall" not in key and not key.startswith("decision_time")}
    if isinstance(value, list):
        return [_without_wall_times(item) for item in value]
    return value


def test_a_saved_world_runs_as_the_seeded_run_it_came_from(tmp_path, capsys):
    world_file = tmp_path / "site.yaml"
    seeded_args = SMALL
    assert sim_cli.main(seeded_args + ["--save-world", str(world_file)]) == 0
    assert f"world: {world_file}" in capsys.readouterr().out
    assert "--seed 5" in world_file.read_text()  # the header says how to run it again
    assert sim_cli.main(seeded_args + ["--summary", str(tmp_path / "seeded.json")]) == 0
    from_file = ["--quiet", "--world", str(world_file), "--seed", "5", "--planner", "NEAREST",
                 "--max-steps", "300", "--summary", str(tmp_path / "from_file.json")]
    assert sim_cli.main(from_file) == 0  # two robots: one per start
    seeded = json.loads((tmp_path / "seeded.json").read_text())
    loaded = json.loads((tmp_path / "from_file.json").read_text())
    assert seeded["decisions"] > 0
    assert _without_wall_times(loaded) == _without_wall_times(seeded)
    # Saving the loaded world writes the same world again.
    again = tmp_path / "again.yaml"
    assert sim_cli.main(["--world", str(world_file), "--save-world", str(again)]) == 0
    body = [line for line in world_file.read_text().splitlines() if not line.startswith("#")]
    assert [line for line in again.read_text().splitlines() if not line.startswith("#")] == body


@pytest.mark.parametrize("name, changes", [
    ("paper_100m_seed0.yaml", {}),
    ("paper_200m_seed0.yaml", {"width_m": 200.0, "height_m": 200.0}),
    ("sparse_200m_seed0.yaml", {"width_m": 200.0, "height_m": 200.0, "num_landmarks": 3}),
])
def test_the_shipped_worlds_are_the_seeded_ones(name, changes):
    params = ExplorationParams().replace(world=changes)
    seeded = generate_world(params.world, params.sensors, run_seed_sequences(0)[0])
    resolved = params_for_world(ExplorationParams(), read_world_file(WORLDS / name),
                                WORLDS / name)
    assert resolved.replace(world={"file": ""}) == params
    world = WorldSimulation(resolved).world
    assert np.array_equal(world.landmarks, seeded.landmarks)
    assert np.array_equal(world.start_poses, seeded.start_poses)
    assert np.array_equal(world.landmark_ids, seeded.landmark_ids)
    assert (world.landmark_radius_m, world.robot_radius_m) == (seeded.landmark_radius_m,
                                                               seeded.robot_radius_m)


def test_a_world_file_sets_the_parameters_it_determines(tmp_path):
    path = tmp_path / "site.yaml"
    path.write_text(json.dumps(GOOD))  # JSON is YAML
    world = read_world_file(path)
    params = params_for_world(ExplorationParams(), world, path)
    assert (params.world.width_m, params.world.height_m, params.world.num_landmarks,
            params.world.num_robots, params.world.file) == (40.0, 30.0, 2, 2, str(path))
    assert params_for_world(ExplorationParams(), world, path, 1).world.num_robots == 1
    # The simulation takes the file's world, or one it is given.
    assert np.array_equal(WorldSimulation(params).world.landmarks,
                          np.array(GOOD["landmarks"])[:, :2])
    given = WorldSimulation(ExplorationParams(), world=world)
    assert given.world is world
    # A node given the file with parameters that do not match it refuses to start.
    with pytest.raises(WorldFileError, match="leave world.width_m"):
        world_for_params(ExplorationParams().replace(world={"file": str(path)}))
    # Every number reads back as the same float, exponents included ("1e-05" is YAML text).
    odd = dict(GOOD, landmarks=[[20.00001, 0.1 + 0.2, "1e-05"]])
    path.write_text(json.dumps(odd))
    with pytest.raises(WorldFileError, match="an exponent without a dot as text: write 1.0e"):
        read_world_file(path)
    path.write_text(json.dumps(odd).replace('"1e-05"', "1.0e-05"))
    world = read_world_file(path)
    assert world.landmarks.tolist() == [[20.00001, 0.30000000000000004]]
    text = world_yaml(world)
    assert "1.0e-05]" in text
    path.write_text(text)
    assert read_world_file(path).landmark_radius_m == 1e-05


def _write(path: Path, data) -> None:
    path.write_text(data if isinstance(data, str) else json.dumps(data))


def _alias_bomb() -> str:
    """Landmarks whose entries are aliases of aliases: entry 9 would expand to 9^8 rows."""
    entries = ["&a0 [1.0, 1.0, 1.0]"] + [f"&a{level} [" + ", ".join([f"*a{level - 1}"] * 9)
                                         + "]" for level in range(1, 10)]
    return ("width_m: 40.0\nheight_m: 30.0\nstarts: [[5.0, 15.0, 0.0]]\n"
            f"landmarks: [{', '.join(entries)}]\n")


#: (file content, the one line's expected part, em-sim's extra arguments)
REFUSALS = [
    (dict(GOOD, landmarks=[[41.0, 5.0, 1.0]]),
     "landmark 0 at (41, 5) m is outside the 40 x 30 m map", []),
    (dict(GOOD, landmarks=[[20.0, -0.5, 1.0]]), "landmark 0 at (20, -0.5) m is outside", []),
    (dict(GOOD, starts=[[5.0, 15.0, 0.0], [5.0, 16.0, 0.0]]),
     "robots 0 and 1 start 1 m apart, closer than two robot radii (1.6 m)", []),
    (dict(GOOD, starts=[[20.0, 16.5, 0.0], [20.0, 19.0, 0.0]]),
     "robot 0 starts at (20, 16.5) m, outside the map or closer than 0.8 + 1 m", []),
    (dict(GOOD, starts=[[0.0, -1.0, 0.0]]), "robot 0 starts at (0, -1) m, outside the map", []),
    (dict(GOOD, starts=[[5.0, 15.0, 0.0], [5.0, 18.0, 0.0], [13.0, 15.0, 0.0]]),
     "robot 2 starts 8 m from robot 0, the nearest robot listed before it, not within the "
     "sonar range 7.5 m", []),
    (GOOD, "it lists 2 starts for 3 robots", ["--robots", "3"]),
    (dict(GOOD, starts=[]), "starts lists 0 entries; between 1 and 26 are allowed", []),
    (dict(GOOD, landmarks=[[20.0, 15.0, 1.0]] * 1001),
     "landmarks lists 1001 entries; between 0 and 1000 are allowed", []),
    (dict(GOOD, landmarks=[[20.0, 15.0, 1.0], [30.0, 5.0, 2.0]]),
     "landmark 1's radius 2 m differs from landmark 0's 1 m", []),
    (dict(GOOD, landmarks=[[20.0, 15.0, 11.0]]), "landmark 0's radius = 11 is outside [0, 10]",
     []),
    ("width_m: .nan\nheight_m: 30.0\nlandmarks: []\nstarts: [[5.0, 15.0, 0.0]]\n",
     "width_m must be finite, got nan", []),
    ("width_m: 40.0\nheight_m: 30.0\nlandmarks: []\nstarts: [[5.0, .inf, 0.0]]\n",
     "starts: entry 0 must be finite, got inf", []),
    ("width_m: 40.0\nheight_m: 30.0\nlandmarks: []\nstarts: [[5.0, 15.0, 1" + "0" * 400
     + "]]\n", "starts: entry 0 must be finite", []),
    (dict(GOOD, width_m="wide"), "width_m must be a number, got 'wide'", []),
    (dict(GOOD, width_m=True), "width_m must be a number, got True", []),
    (dict(GOOD, width_m=5.0), "width_m = 5 is outside [10, 2000]", []),
    (dict(GOOD, landmarks="none"), "landmarks must be a list of [x [m], y [m], radius [m]]",
     []),
    (dict(GOOD, starts=[[5.0, 15.0]]), "starts: entry 0 must be [x [m], y [m], yaw [rad]], "
     "got [5.0, 15.0]", []),
    (dict(GOOD, starts=[[5.0, "north", 0.0]]), "starts: entry 0 must be a number, got 'north'",
     []),
    (dict(GOOD, widht_m=3.0), "unknown key 'widht_m' (did you mean 'width_m'?)", []),
    ({k: v for k, v in GOOD.items() if k != "starts"}, "lacks starts", []),
    ([1, 2], "must be a mapping with the keys width_m, height_m, landmarks, starts", []),
    ("width_m: 40.0\nwidth_m: 40.0\n", "duplicate key 'width_m' at line 2 (first at line 1)", []),
    ("width_m: [40.0\n", "is not valid YAML: while parsing a flow sequence", []),
    (_alias_bomb(), "landmarks: entry 1 must be [x [m], y [m], radius [m]], got [[1.0, 1.0, "
     "1.0], [1.0, 1.0, 1.0], [1.0, 1.0, 1.0], [1.0, 1.0, 1.0], ...]", []),
    ("landmarks: [" + "[1.0, 1.0, 1.0], " * 1_000_000 + "]\n",  # a million landmarks
     f"is too large (17000014 bytes, at most {MAX_FILE_BYTES})", []),
    (b"\xff\xfe\x00", "is not UTF-8 text", []),
]


@pytest.mark.parametrize("content, message, extra", REFUSALS)
def test_em_sim_refuses_a_bad_world_file_in_one_line(tmp_path, capsys, content, message,
                                                     extra):
    path = tmp_path / "world.yaml"
    if isinstance(content, bytes):
        path.write_bytes(content)
    else:
        _write(path, content)
    assert sim_cli.main(["--quiet", "--world", str(path), *extra]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith(f"em-sim: error: world file {path}"), err
    assert message in err, err


@pytest.mark.parametrize("kind", ["missing", "folder", "fifo"])
def test_em_sim_refuses_what_is_no_world_file(tmp_path, capsys, kind):
    path = tmp_path / "world.yaml"
    if kind == "folder":
        path.mkdir()
    elif kind == "fifo":
        os.mkfifo(path)  # opening it for reading would wait for a writer for ever
    assert sim_cli.main(["--quiet", "--world", str(path)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and f"world file {path}: cannot read it" in err, err


def test_em_sim_refuses_a_world_file_with_a_map_size(tmp_path, capsys):
    path = tmp_path / "world.yaml"
    _write(path, GOOD)
    with pytest.raises(SystemExit) as exit_info:
        sim_cli.main(["--world", str(path), "--map-size", "60"])
    assert exit_info.value.code == 2
    assert "--world gives the map size and the landmarks" in capsys.readouterr().err


def test_em_bench_refuses_a_bad_world_file_before_any_trial(tmp_path, capsys):
    path = tmp_path / "world.yaml"
    _write(path, dict(GOOD, landmarks=[[41.0, 5.0, 1.0]]))
    out = tmp_path / "bench"
    assert bench.main(["planners", "--world", str(path), "--planners", "NEAREST",
                       "--trials", "1", "--out", str(out)]) == 2
    assert capsys.readouterr().err.splitlines() == [
        f"em-bench: error: world file {path}: landmark 0 at (41, 5) m is outside the "
        "40 x 30 m map", "Try 'em-bench --help'."]
    assert not (out / "trials").exists()


def test_em_bench_runs_trials_on_a_world_file(tmp_path):
    path = tmp_path / "world.yaml"
    _write(path, GOOD)
    out = tmp_path / "bench"
    args = bench.build_parser().parse_args(["planners", "--world", str(path), "--planners",
                                            "NEAREST", "CE", "--trials", "2", "--out",
                                            str(out)])
    specs = bench.trial_specs(args, out)
    assert len(specs) == 4
    assert {spec.params.world.file for spec in specs} == {str(path)}
    assert {(spec.params.world.width_m, spec.params.world.num_robots) for spec in specs} == {
        (40.0, 2)}
    assert {spec.setting for spec in specs} == {"world_40x30m_cell0.8m"}  # the file's stem first


def test_run_team_refuses_a_bad_world_file_before_starting(tmp_path):
    path = tmp_path / "world.yaml"
    _write(path, dict(GOOD, starts=[[5.0, 15.0, 0.0], [5.0, 15.5, 0.0]]))
    result = subprocess.run(["bash", str(RUN_TEAM), "--world", str(path)], capture_output=True,
                            text=True, timeout=60, stdin=subprocess.DEVNULL)
    assert result.returncode == 2, result.stderr
    lines = [line for line in result.stderr.splitlines() if not line.startswith("setup:")]
    assert lines == [f"run_team.sh: error: invalid parameters: world file {path}: robots 0 "
                     "and 1 start 0.5 m apart, closer than two robot radii (1.6 m)"], lines
    assert "logs in" not in result.stdout  # no process was started
    result = subprocess.run(["bash", str(RUN_TEAM), "--world", str(path), "--landmarks", "3"],
                            capture_output=True, text=True, timeout=60, stdin=subprocess.DEVNULL)
    assert result.returncode == 2 and "--world gives the map size" in result.stderr
