"""The command line's outputs under faults (issue 13, findings 5, 6, 7): a full disk, an I/O
error, a read-only folder or a directory in the way is one line and exit status 2 with nothing
left behind; the outputs and the exit status agree; an output that is an input is refused unless
--force; export writes .png/.svg; solve on a map says which command opens it."""

from __future__ import annotations

import errno
import os
import shutil
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

import pytest

from hitl_slam.cli import main
from hitl_slam.io import atomic
from hitl_slam.io.export import export
from hitl_slam.sim.corridor import corridor_loop

Fault = Callable[[pytest.MonkeyPatch], None]


@pytest.fixture(scope="module")
def map_source(tmp_path_factory: pytest.TempPathFactory) -> Path:
    world = corridor_loop(seed=1)
    path = tmp_path_factory.mktemp("map") / "corridor.covars"
    export(world.map, world.map.poses, path)
    return path


@pytest.fixture
def inputs(map_source: Path, tmp_path: Path) -> Path:
    """A folder holding the map, an empty corrections file and a small pose graph."""
    folder = tmp_path / "in"
    folder.mkdir()
    shutil.copy(map_source, folder / "corridor.covars")
    (folder / "none.jsonl").write_text("")
    assert main(["generate", str(folder / "g.g2o"), "--poses", "60"]) == 0
    return folder


def fail(name: str, code: int) -> Fault:
    def apply(monkeypatch: pytest.MonkeyPatch) -> None:
        def refuse(*_args: object, **_kwargs: object) -> None:
            raise OSError(code, os.strerror(code))

        monkeypatch.setattr(os, name, refuse)

    return apply


def read_only(monkeypatch: pytest.MonkeyPatch) -> None:
    real_open = os.open

    def refuse(path: str, flags: int, *args: object, **kwargs: object) -> int:
        if flags & os.O_CREAT:
            raise OSError(errno.EROFS, os.strerror(errno.EROFS), path)
        return real_open(path, flags, *args, **kwargs)  # type: ignore[arg-type]

    monkeypatch.setattr(os, "open", refuse)


FAULTS: dict[str, Fault] = {
    "ENOSPC": fail("fsync", errno.ENOSPC),
    "EIO on rename": fail("replace", errno.EIO),
    "read-only": read_only,
}

# (arguments given the input folder I and output folder O, the files the command writes)
COMMANDS: dict[str, tuple[Callable[[Path, Path], list[str]], list[str]]] = {
    "export covars": (lambda i, o: ["export", f"{i}/corridor.covars", "-o", f"{o}/m.covars"], []),
    "export pgm": (lambda i, o: ["export", f"{i}/corridor.covars", "-o", f"{o}/m.pgm"], []),
    "export png": (lambda i, o: ["export", f"{i}/corridor.covars", "-o", f"{o}/m.png"], []),
    "export txt": (lambda i, o: ["export", f"{i}/corridor.covars", "-o", f"{o}/m.txt"], []),
    "solve": (lambda i, o: ["solve", f"{i}/g.g2o", "-o", f"{o}/s.g2o", "-q"], []),
    "generate": (lambda i, o: ["generate", f"{o}/n.g2o", "--poses", "30"], []),
    "heat map": (
        lambda i, o: ["metrics", f"{i}/corridor.covars", "--heat-map", f"{o}/h.png", "-q"],
        [],
    ),
    "correct": (
        lambda i, o: [
            "correct",
            f"{i}/corridor.covars",
            "--corrections",
            f"{i}/none.jsonl",
            "-o",
            f"{o}/c.pgm",
            "-q",
        ],
        [],
    ),
}


def one_line_error(err: str) -> str:
    assert err.count("\n") == 1, err
    assert err.startswith("hitl-slam: error: "), err
    assert "Traceback" not in err
    return err


@pytest.mark.parametrize("fault", list(FAULTS))
@pytest.mark.parametrize("command", list(COMMANDS))
def test_an_output_fault_is_one_line_exit_2_and_nothing_left(
    inputs: Path,
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
    command: str,
    fault: str,
) -> None:
    out = tmp_path / "out"
    out.mkdir()
    args = COMMANDS[command][0](inputs, out)
    capsys.readouterr()
    FAULTS[fault](monkeypatch)
    code = main(args)
    monkeypatch.undo()
    err = capsys.readouterr().err
    assert code == 2, err
    one_line_error(err)
    assert os.listdir(out) == []


@pytest.mark.parametrize("command", list(COMMANDS))
def test_a_directory_as_output_is_one_line_exit_2(
    inputs: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str], command: str
) -> None:
    out = tmp_path / "out"
    out.mkdir()
    args = COMMANDS[command][0](inputs, out)
    target = Path(args[args.index("-o") + 1] if "-o" in args else args[1])
    if "--heat-map" in args:
        target = Path(args[args.index("--heat-map") + 1])
    target.mkdir()
    capsys.readouterr()
    assert main(args) == 2
    err = one_line_error(capsys.readouterr().err)
    assert "directory" in err.lower()
    assert os.listdir(out) == [target.name]
    assert os.listdir(target) == []


def test_a_failed_yaml_takes_its_pgm_with_it(
    inputs: Path,
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
) -> None:
    """Exit 2 means nothing written: the .pgm is not left without its .yaml (finding 6)."""
    out = tmp_path / "out"
    out.mkdir()
    (out / "m.pgm").write_bytes(b"old pgm")
    real_replace = os.replace

    def replace(src: str, dst: str) -> None:
        if str(dst).endswith(".yaml"):
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        real_replace(src, dst)

    monkeypatch.setattr(os, "replace", replace)
    assert main(["export", f"{inputs}/corridor.covars", "-o", f"{out}/m.pgm"]) == 2
    monkeypatch.undo()
    one_line_error(capsys.readouterr().err)
    assert (out / "m.pgm").read_bytes() == b"old pgm"
    assert os.listdir(out) == ["m.pgm"]


def test_a_session_that_cannot_be_written_leaves_no_output(
    inputs: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Finding 6: `correct --session` used to write OUT, then fail on the session: exit 2 with
    OUT written. Now both or neither."""
    out = tmp_path / "out"
    out.mkdir()
    code = main(
        [
            "correct",
            f"{inputs}/corridor.covars",
            "--corrections",
            f"{inputs}/none.jsonl",
            "-o",
            f"{out}/fixed.covars",
            "--session",
            f"{out}/missing-folder/run.hitl",
            "-q",
        ]
    )
    assert code == 2
    one_line_error(capsys.readouterr().err)
    assert os.listdir(out) == []


def test_an_output_that_cannot_be_renamed_takes_the_new_session_with_it(
    inputs: Path,
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
) -> None:
    out = tmp_path / "out"
    out.mkdir()
    real_replace = os.replace

    def replace(src: str, dst: str) -> None:
        if str(dst).endswith("fixed.covars"):
            raise OSError(errno.EIO, os.strerror(errno.EIO))
        real_replace(src, dst)

    monkeypatch.setattr(os, "replace", replace)
    args = ["correct", f"{inputs}/corridor.covars", "--corrections", f"{inputs}/none.jsonl"]
    code = main([*args, "-o", f"{out}/fixed.covars", "--session", f"{out}/run.hitl", "-q"])
    monkeypatch.undo()
    assert code == 2
    assert "I/O error" in one_line_error(capsys.readouterr().err)
    assert os.listdir(out) == []
    assert main([*args, "-o", f"{out}/fixed.covars", "--session", f"{out}/run.hitl", "-q"]) == 0
    assert sorted(os.listdir(out)) == ["fixed.covars", "run.hitl"]


# --------------------------------------------------------------------------------------------
# Output = input (finding 7)


@pytest.mark.parametrize("how", ["same name", "symbolic link", "hard link"])
def test_an_output_that_is_the_input_is_refused_unless_force(
    inputs: Path, capsys: pytest.CaptureFixture[str], how: str
) -> None:
    source = inputs / "corridor.covars"
    before = source.read_bytes()
    out = source
    if how == "symbolic link":
        out = inputs / "link.covars"
        out.symlink_to(source)
    elif how == "hard link":
        out = inputs / "hard.covars"
        os.link(source, out)
    capsys.readouterr()
    args = ["correct", str(source), "--corrections", f"{inputs}/none.jsonl", "-o", str(out), "-q"]
    assert main(args) == 2
    err = one_line_error(capsys.readouterr().err)
    assert "--force" in err
    assert "replace the input" in err
    assert source.read_bytes() == before
    assert main(["export", str(source), "-o", str(out)]) == 2
    one_line_error(capsys.readouterr().err)
    assert main([*args, "--force"]) == 0
    assert out.is_file()


def test_solve_refuses_to_overwrite_its_graph(
    inputs: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    graph = inputs / "g.g2o"
    before = graph.read_text()
    capsys.readouterr()
    assert main(["solve", str(graph), "-o", str(graph), "-q"]) == 2
    assert "--force" in one_line_error(capsys.readouterr().err)
    assert graph.read_text() == before
    assert main(["solve", str(graph), "-o", str(graph), "-q", "--force"]) == 0
    assert graph.read_text() != before


def test_a_pgm_whose_yaml_is_an_input_is_refused(
    inputs: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    (inputs / "c.yaml").symlink_to(inputs / "corridor.covars")
    capsys.readouterr()
    assert main(["export", f"{inputs}/corridor.covars", "-o", f"{inputs}/c.pgm"]) == 2
    assert "c.yaml" in one_line_error(capsys.readouterr().err)


# --------------------------------------------------------------------------------------------
# Formats and hints (finding 7)


@pytest.mark.parametrize(("extension", "magic"), [(".png", b"\x89PNG"), (".svg", b"<?xml")])
def test_export_writes_the_figure_formats_it_lists(
    inputs: Path, tmp_path: Path, extension: str, magic: bytes
) -> None:
    out = tmp_path / f"map{extension}"
    assert main(["export", f"{inputs}/corridor.covars", "-o", str(out), "-q"]) == 0
    assert out.read_bytes().startswith(magic)
    assert sorted(os.listdir(tmp_path)) == sorted([out.name, "in"])


@pytest.mark.parametrize("name", ["run.clf", "run.log.gz", "run.covars", "run.hitl"])
def test_solve_on_a_map_says_which_command_opens_it(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], name: str
) -> None:
    path = tmp_path / name
    path.write_text("PARAM robot_front_laser_max 80\n")
    assert main(["solve", str(path), "-o", str(tmp_path / "out.g2o")]) == 2
    err = one_line_error(capsys.readouterr().err)
    assert "not a pose graph" in err
    assert "hitl-slam correct" in err
    assert "hitl-slam export" in err


def test_solve_on_a_carmen_log_by_another_name(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = tmp_path / "run.txt"
    path.write_text("# a log\nPARAM robot_front_laser_max 80\nODOM 0 0 0 0 0 0 1.0 h 1.0\n")
    assert main(["solve", str(path), "-o", str(tmp_path / "out.g2o")]) == 2
    err = one_line_error(capsys.readouterr().err)
    assert "CARMEN log" in err
    assert "hitl-slam correct" in err


# --------------------------------------------------------------------------------------------
# Temporary files of killed runs


def test_the_cli_sweeps_and_reports_stale_temporary_files(
    inputs: Path,
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
) -> None:
    monkeypatch.setattr(atomic, "_SWEPT", set())
    child = subprocess.Popen([sys.executable, "-c", "pass"])
    child.wait()
    out = tmp_path / "out"
    out.mkdir()
    stale = out / f".m.covars.{child.pid}-0123abcd.hitl-tmp"
    stale.write_bytes(b"\0" * 4096)
    past = time.time() - 3600
    os.utime(stale, (past, past))
    assert main(["export", f"{inputs}/corridor.covars", "-o", f"{out}/m.covars", "-q"]) == 0
    err = capsys.readouterr().err
    assert f"hitl-slam: removed {stale}" in err
    assert os.listdir(out) == ["m.covars"]


# --------------------------------------------------------------------------------------------
# A real full and a real read-only file system (a small tmpfs in a private mount namespace)


def _namespace_available() -> bool:
    if not sys.platform.startswith("linux") or shutil.which("unshare") is None:
        return False
    probe = ["unshare", "--mount", "--map-root-user", "sh", "-c", "mount -t tmpfs t /mnt"]
    try:
        return subprocess.run(probe, capture_output=True, timeout=10).returncode == 0
    except (OSError, subprocess.TimeoutExpired):
        return False


@pytest.mark.skipif(not _namespace_available(), reason="no unshare/mount namespace here")
@pytest.mark.parametrize(("options", "reason"), [("size=64k", "No space"), ("ro", "Read-only")])
def test_a_real_full_or_read_only_file_system(
    inputs: Path, tmp_path: Path, options: str, reason: str
) -> None:
    out = tmp_path / "out"
    out.mkdir()
    cli = f"{sys.executable} -m hitl_slam.cli"
    script = (
        f"mount -t tmpfs -o {options} t {out} || exit 99\n"
        f"{cli} export {inputs}/corridor.covars -o {out}/m.covars; echo rc=$?\n"
        f"{cli} export {inputs}/corridor.covars -o {out}/m.pgm; echo rc=$?\n"
        f"{cli} correct {inputs}/corridor.covars --corrections {inputs}/none.jsonl "
        f"-o {out}/c.covars -q; echo rc=$?\n"
        f"echo listing; ls -A {out}; echo end\n"
    )
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(sys.path)}
    run = subprocess.run(
        ["unshare", "--mount", "--map-root-user", "sh", "-c", script],
        capture_output=True,
        text=True,
        env=env,
        timeout=300,
        check=False,
    )
    assert run.returncode != 99, run.stderr
    lines = run.stdout.splitlines()
    rcs = [line for line in lines if line.startswith("rc=")]
    left = set(lines[lines.index("listing") + 1 : lines.index("end")])
    assert "Traceback" not in run.stderr
    if options == "ro":
        assert rcs == ["rc=2", "rc=2", "rc=2"], run.stdout + run.stderr
        assert left == set()
    else:
        # 64 KiB: the .covars (MBs) cannot fit; the .pgm and .yaml may, and are then whole.
        assert rcs[0] == "rc=2", run.stdout + run.stderr
        assert rcs[2] == "rc=2", run.stdout + run.stderr
        assert left <= {"m.pgm", "m.yaml"}
        assert (rcs[1] == "rc=0") == (left == {"m.pgm", "m.yaml"})
    errors = run.stderr.strip().splitlines()
    assert all(e.startswith("hitl-slam: error: ") and reason in e for e in errors), run.stderr
