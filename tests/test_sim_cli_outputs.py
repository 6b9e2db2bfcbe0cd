"""em-sim's output files: checked before the run, written whole or not at all after it."""
import errno
import logging
import os
from pathlib import Path

import pytest

from em_exploration_ros.core.output_paths import output_path_problem, write_replacing
from em_exploration_ros.tools import sim_cli

SMALL_RUN = ["--quiet", "--map-size", "40", "--landmarks", "4", "--max-steps", "20"]


def test_output_path_problem_follows_links_and_refuses_devices_and_wrong_suffixes(tmp_path):
    dangling = tmp_path / "dangling.json"
    dangling.symlink_to(tmp_path / "absent" / "x.json")
    assert "the folder" in output_path_problem(dangling, "--summary")
    assert "is not a regular file" in output_path_problem("/dev/full", "--summary")
    assert "must end in .png" in output_path_problem(tmp_path / "map.xyz", "--map", ".png")
    assert "must end in .png" in output_path_problem(tmp_path / "teammap", "--map", ".png")
    (tmp_path / "X.png").mkdir()
    assert "is a directory" in output_path_problem(tmp_path / "X.png", "--map", ".png")
    assert output_path_problem(tmp_path / "map.PNG", "--map", ".png") is None


def _fail_after_partial_write(path: Path) -> None:
    path.write_text('{"partial": ')
    raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))


def test_write_replacing_keeps_the_old_file_when_the_write_fails(tmp_path):
    target = tmp_path / "run.json"
    target.write_text("old\n")
    with pytest.raises(OSError, match="No space left"):
        write_replacing(target, _fail_after_partial_write)
    assert target.read_text() == "old\n" and os.listdir(tmp_path) == ["run.json"]
    write_replacing(target, lambda path: path.write_text("new\n"))
    assert target.read_text() == "new\n" and os.listdir(tmp_path) == ["run.json"]
    umask = os.umask(0)
    os.umask(umask)
    assert target.stat().st_mode & 0o777 == 0o666 & ~umask


def _no_run(*args: object) -> None:
    raise AssertionError("the run must not start")


@pytest.mark.parametrize("args, message", [
    (["--summary", "{tmp}/dangling.json"], "--summary {tmp}/dangling.json (-> "),
    (["--summary", "/dev/full"], "--summary /dev/full is not a regular file"),
    (["--map", "{tmp}/out.xyz"], "--map {tmp}/out.xyz must end in .png"),
    (["--map", "{tmp}/teammap"], "--map {tmp}/teammap must end in .png"),
    (["--map", "{tmp}/X.png"], "--map {tmp}/X.png is a directory"),
    (["--summary", "{tmp}/F.png", "--map", "{tmp}/F.png"],
     "--summary and --map name the same file {tmp}/F.png"),
])
def test_em_sim_refuses_bad_outputs_before_the_run(tmp_path, capsys, args, message):
    (tmp_path / "dangling.json").symlink_to(tmp_path / "absent" / "x.json")
    (tmp_path / "X.png").mkdir()
    with pytest.raises(SystemExit) as exited:
        sim_cli.main(SMALL_RUN + [arg.format(tmp=tmp_path) for arg in args], make_runner=_no_run)
    assert exited.value.code == 2
    assert message.format(tmp=tmp_path) in capsys.readouterr().err


@pytest.mark.parametrize("option", ["--summary", "--map"])
def test_em_sim_reports_a_write_failing_after_the_run_in_one_line(tmp_path, capsys, caplog,
                                                                  option):
    summary, team_map = tmp_path / "run.json", tmp_path / "map.png"
    failed = summary if option == "--summary" else team_map

    def write_file(path: Path, write) -> None:  # the output ``option`` fails half-written
        write_replacing(path, _fail_after_partial_write if path == failed else write)

    with caplog.at_level(logging.ERROR):
        code = sim_cli.main(SMALL_RUN + ["--summary", str(summary), "--map", str(team_map)],
                            write_file=write_file)
    assert code == sim_cli.EXIT_WRITE_FAILED
    assert [record.getMessage() for record in caplog.records] == [
        f"cannot write {option} {failed}: No space left on device"]
    assert not failed.exists() and sorted(os.listdir(tmp_path)) == sorted(
        {summary.name, team_map.name} - {failed.name})
    assert f": {failed}" not in capsys.readouterr().out  # not reported as written
