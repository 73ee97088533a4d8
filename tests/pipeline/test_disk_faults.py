"""Faults on disk: a write the disk refuses stops its stage with one line and keeps every complete output; a damaged,
cut or hand-edited output is found from its manifest's hashes and made again; a checkpoint is read only by the code
and settings that wrote it; a file is written whole or not at all."""
import errno
import json
import os
from pathlib import Path

import pytest

from pipeline import cli
from pipeline.report import Reporter
from pipeline.runner import Pipeline
from pipeline.stage import StageGraph
from plenoxels.core.errors import UserError
from plenoxels.core.files import write_whole
from tests.pipeline.test_cache import SOURCES as CACHE_SOURCES, stage_package
from stages.common.text import format_bytes

# a -> b -> c. b fails as the scene's FAIL file says (an errno, or a library's message), and keeps a checkpoint in its
# scratch folder that it reports on.
SOURCES = {
    "__init__.py": "",
    "a.py": '''
        from dataclasses import dataclass
        NAME, DEPENDS, VERSION = "a", (), 1
        @dataclass
        class Settings:
            value: int = 1
        def run(ctx):
            (ctx.work / "a.txt").write_text("a" * 1000)
            return {"line": "a done"}
    ''',
    "b.py": '''
        import errno, os
        from dataclasses import dataclass
        NAME, DEPENDS, VERSION = "b", ("a",), 1
        @dataclass
        class Settings:
            value: int = 1
        def run(ctx):
            resumed = (ctx.scratch / "checkpoint").is_file()
            (ctx.scratch / "checkpoint").write_text("step 10")
            (ctx.work / "b.txt").write_text("b" * 5000)
            fail = ctx.scene / "FAIL"
            if fail.is_file():
                how = fail.read_text()
                if how.isdigit():
                    raise OSError(int(how), os.strerror(int(how)), str(ctx.work / "b.txt"))
                raise RuntimeError(how)
            return {"line": "b done", "resumed": resumed}
    ''',
    "c.py": CACHE_SOURCES["c.py"],  # the same last stage as the cache tests'
}


@pytest.fixture
def package(tmp_path, monkeypatch):
    return stage_package(tmp_path, monkeypatch, "diskstages", SOURCES)


def make(tmp_path, *overrides: str) -> Pipeline:
    (tmp_path / "scene").mkdir(exist_ok=True)
    return Pipeline(tmp_path / "scene", tmp_path / "out", overrides=list(overrides), reporter=Reporter(quiet=True),
                    graph=StageGraph(package="diskstages", order=("a", "b", "c"), declarations=None))


def contents(folder: Path) -> dict[str, bytes]:
    return {p.relative_to(folder).as_posix(): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def run_ids(out: Path) -> dict[str, str]:
    return {name: json.loads((out / name / "manifest.json").read_text())["run_id"] for name in ("a", "b", "c")}


@pytest.mark.parametrize("failure", [str(errno.ENOSPC), str(errno.EDQUOT), str(errno.EROFS), str(errno.EIO),
                                     "filesystem error: cannot copy file: No space left on device"])
def test_a_refused_write_stops_with_one_line_keeps_what_is_complete_and_the_same_command_goes_on(package, tmp_path,
                                                                                                failure):
    make(tmp_path).run(["a"])
    before = contents(tmp_path / "out" / "a")
    (tmp_path / "scene" / "FAIL").write_text(failure)
    with pytest.raises(UserError) as stopped:
        make(tmp_path).run(["c"])
    line = str(stopped.value)
    assert "\n" not in line and line.startswith("the b stage could not write ")
    assert "run the same command again" in line and " free; " in line and f"written {format_bytes(5000)}" in line
    assert contents(tmp_path / "out" / "a") == before
    assert not (tmp_path / "out" / "b").exists() and not (tmp_path / "out" / ".work" / "b").exists()

    (tmp_path / "scene" / "FAIL").unlink()
    make(tmp_path).run(["c"])
    assert contents(tmp_path / "out" / "a") == before
    assert (tmp_path / "out" / "c" / "c.txt").read_text() == "b" * 5000


def test_an_error_that_is_not_the_disks_is_not_dressed_as_one(package, tmp_path):
    (tmp_path / "scene").mkdir()
    (tmp_path / "scene" / "FAIL").write_text("a bug in the stage")
    with pytest.raises(RuntimeError, match="a bug in the stage"):
        make(tmp_path).run(["b"])


@pytest.mark.parametrize("damage", ["truncate", "edit", "delete"])
def test_a_damaged_output_is_named_and_its_stage_and_those_after_it_run_again(package, tmp_path, damage):
    make(tmp_path).run(["c"])
    first = run_ids(tmp_path / "out")
    target = tmp_path / "out" / "b" / "b.txt"
    if damage == "truncate":
        target.write_bytes(target.read_bytes()[:100])
    elif damage == "edit":  # the same size, one byte changed, as a hand edit might
        target.write_bytes(b"x" + target.read_bytes()[1:])
    else:
        target.unlink()
    state, why = make(tmp_path).status("b")
    assert state == "stale" and "b/b.txt" in why
    make(tmp_path).run(["c"])
    again = run_ids(tmp_path / "out")
    assert again["a"] == first["a"] and again["b"] != first["b"] and again["c"] != first["c"]
    assert target.read_text() == "b" * 5000
    assert make(tmp_path).status("b")[0] == "done"


def test_a_manifest_cut_short_counts_as_missing(package, tmp_path):
    make(tmp_path).run(["c"])
    first = run_ids(tmp_path / "out")
    manifest = tmp_path / "out" / "b" / "manifest.json"
    manifest.write_bytes(manifest.read_bytes()[:40])
    assert make(tmp_path).status("b")[0] == "missing"
    make(tmp_path).run(["c"])
    again = run_ids(tmp_path / "out")
    assert again["a"] == first["a"] and again["b"] != first["b"]


def test_a_checkpoint_is_read_only_by_the_settings_that_wrote_it(package, tmp_path):
    (tmp_path / "scene").mkdir()
    (tmp_path / "scene" / "FAIL").write_text(str(errno.ENOSPC))
    with pytest.raises(UserError):
        make(tmp_path).run(["b"])
    (tmp_path / "scene" / "FAIL").unlink()
    other = make(tmp_path, "b.value=2").run(["b"])["b"]
    assert other["summary"]["resumed"] is False

    (tmp_path / "scene" / "FAIL").write_text(str(errno.ENOSPC))
    with pytest.raises(UserError):
        make(tmp_path).run(["b"])
    (tmp_path / "scene" / "FAIL").unlink()
    same = make(tmp_path).run(["b"])["b"]
    assert same["summary"]["resumed"] is True


def test_the_command_line_turns_a_refused_write_into_one_line(monkeypatch, capsys):
    def refuse(args):
        raise OSError(errno.EROFS, os.strerror(errno.EROFS), "/media/card/out/.lock")
    monkeypatch.setattr("pipeline.commands.status.main", refuse)
    assert cli.main(["status", "somewhere"]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and err.startswith("error: cannot use /media/card/out/.lock: the file system is read-only")


def test_a_file_is_written_whole_or_not_at_all(tmp_path):
    target = tmp_path / "grid.pt"
    target.write_bytes(b"old" * 100)

    def fails_halfway(tmp):
        Path(tmp).write_bytes(b"new" * 10)
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(tmp))

    with pytest.raises(OSError):
        write_whole(target, fails_halfway)
    assert target.read_bytes() == b"old" * 100 and [p.name for p in tmp_path.iterdir()] == ["grid.pt"]
    write_whole(target, lambda tmp: Path(tmp).write_bytes(b"new" * 10))
    assert target.read_bytes() == b"new" * 10 and [p.name for p in tmp_path.iterdir()] == ["grid.pt"]
