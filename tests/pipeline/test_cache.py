"""Cache keys see code: editing any project module a stage imports makes that stage and those after it stale."""
import ast
import sys
import textwrap
from pathlib import Path

import pytest

import pipeline.runner as runner
from pipeline.report import Reporter
from pipeline.runner import Pipeline
from pipeline.stage import STAGE_ORDER, StageGraph, code_hash, import_closure
from plenoxels.core.memory import MemoryLimit
from stages.common.layout import MEMORY_AS_SET

# a -> b -> c; b reaches `shapes` only through `helpers` (and a relative import), so the key must follow imports
# transitively; `unrelated` is imported by no stage.
SOURCES = {
    "__init__.py": "",
    "shapes.py": "SIDE = 2\n",
    "helpers.py": "from .shapes import SIDE\n\ndef area():\n    return SIDE * SIDE\n",
    "unrelated.py": "X = 1\n",
    "a.py": '''
        from dataclasses import dataclass
        NAME, DEPENDS, VERSION = "a", (), 1
        @dataclass
        class Settings:
            value: int = 1
        def run(ctx):
            (ctx.work / "a.txt").write_text(str(ctx.settings.value))
            return {"line": "a done"}
    ''',
    "b.py": '''
        from dataclasses import dataclass
        from cachestages import helpers
        NAME, DEPENDS, VERSION = "b", ("a",), 1
        @dataclass
        class Settings:
            pass
        def run(ctx):
            (ctx.work / "b.txt").write_text(str(helpers.area()))
            return {"line": "b done"}
    ''',
    "c.py": '''
        from dataclasses import dataclass
        NAME, DEPENDS, VERSION = "c", ("b",), 1
        @dataclass
        class Settings:
            pass
        def run(ctx):
            (ctx.work / "c.txt").write_text((ctx.upstream["b"] / "b.txt").read_text())
            return {"line": "c done"}
    ''',
}


def stage_package(tmp_path, monkeypatch, name: str, sources: dict[str, str]) -> Path:
    """A package of tiny stages written under tmp_path and importable as `name`, fresh (no module of an earlier test's
    package of that name is left imported)."""
    root = tmp_path / "pkg" / name
    root.mkdir(parents=True)
    for file, source in sources.items():
        (root / file).write_text(textwrap.dedent(source))
    monkeypatch.syspath_prepend(str(tmp_path / "pkg"))
    for mod in [m for m in sys.modules if m.startswith(name)]:
        del sys.modules[mod]
    return root


@pytest.fixture
def package(tmp_path, monkeypatch):
    return stage_package(tmp_path, monkeypatch, "cachestages", SOURCES)


def make(tmp_path) -> Pipeline:
    (tmp_path / "scene").mkdir(exist_ok=True)
    return Pipeline(tmp_path / "scene", tmp_path / "out", reporter=Reporter(quiet=True),
                    graph=StageGraph(package="cachestages", order=("a", "b", "c"), declarations=None))


def statuses(pipe: Pipeline) -> dict[str, tuple[str, str]]:
    return {name: pipe.status(name) for name in ("a", "b", "c")}


def test_the_closure_follows_imports_transitively(package):
    closure = import_closure("cachestages.b")
    assert {"cachestages", "cachestages.b", "cachestages.helpers", "cachestages.shapes"} <= set(closure)
    assert "cachestages.unrelated" not in closure and "dataclasses" not in closure


def test_editing_a_helper_makes_its_stage_and_those_after_it_stale(package, tmp_path, capsys):
    make(tmp_path).run(["c"])
    assert all(state == "done" for state, _ in statuses(make(tmp_path)).values())

    (package / "shapes.py").write_text("SIDE = 10\n")
    after = statuses(make(tmp_path))
    assert after["a"][0] == "done"
    assert after["b"] == ("stale", "code changed")
    assert after["c"] == ("stale", "b will re-run")

    capsys.readouterr()
    for mod in [m for m in sys.modules if m.startswith("cachestages")]:
        del sys.modules[mod]  # a new process would import the edited source
    make(tmp_path).run(["c"])
    out = capsys.readouterr().out
    assert "[a] up to date" in out and "[b] b done" in out and "[c] c done" in out
    assert (tmp_path / "out" / "c" / "c.txt").read_text() == "100"


def test_editing_an_unrelated_module_changes_nothing(package, tmp_path):
    make(tmp_path).run(["c"])
    keys = {name: make(tmp_path).plan(name).key for name in ("a", "b", "c")}
    (package / "unrelated.py").write_text("X = 2\n")
    assert {name: make(tmp_path).plan(name).key for name in ("a", "b", "c")} == keys
    assert all(state == "done" for state, _ in statuses(make(tmp_path)).values())


def test_every_project_module_a_stage_imports_is_in_its_key():
    # The camera convention, imported only through the library, must be in every key that depends on it.
    for name in ("normalize", "fit", "evaluate", "export"):
        assert "plenoxels.core.cameras" in import_closure(f"stages.{name}")


def test_stages_that_load_the_native_core_hash_its_sources(tmp_path, monkeypatch):
    import pipeline.stage as stage

    assert "plenoxels.core.native" in import_closure("stages.fit")
    csrc = tmp_path / "csrc"
    csrc.mkdir()
    (csrc / "kernel.cpp").write_text("int f() { return 1; }\n")
    monkeypatch.setattr(stage, "NATIVE_SOURCES", csrc)
    before = code_hash(["stages.fit"], 1)  # hashed from source; no need to import it
    (csrc / "kernel.cpp").write_text("int f() { return 2; }\n")
    assert code_hash(["stages.fit"], 1) != before


def test_no_stage_lists_its_code_by_hand():
    stages_dir = Path(__file__).resolve().parents[2] / "stages"
    listed = [name for name in STAGE_ORDER
              if any(isinstance(node, ast.Assign) and any(getattr(t, "id", None) == "CODE" for t in node.targets)
                     for node in ast.parse((stages_dir / f"{name}.py").read_text()).body)]
    assert listed == [], "the cache key follows imports; delete CODE"



# c as a stage that lowers its settings to fit in memory each time it runs, and counts its runs.
LOWERING_SOURCES = dict(SOURCES, **{"c.py": f'''
    from dataclasses import dataclass
    NAME, DEPENDS, VERSION = "c", ("b",), 1
    @dataclass
    class Settings:
        pass
    def run(ctx):
        runs = ctx.out / "c_runs"
        runs.write_text(str(int(runs.read_text()) + 1 if runs.is_file() else 1))
        return {{"line": "c done, lowered to fit in memory", {MEMORY_AS_SET!r}: 3 << 30}}
'''})


def test_an_output_lowered_to_fit_in_memory_is_made_again_once_that_memory_is_there(tmp_path, monkeypatch, capsys):
    stage_package(tmp_path, monkeypatch, "cachestages", LOWERING_SOURCES)
    monkeypatch.setattr(runner, "memory_limit", lambda: MemoryLimit(2 << 30, "cgroup memory.max"))
    make(tmp_path).run(["c"])
    make(tmp_path).run(["c"])  # still 2 GiB: kept, however lesser
    assert (tmp_path / "out" / "c_runs").read_text() == "1" and make(tmp_path).status("c")[0] == "done"

    monkeypatch.setattr(runner, "memory_limit", lambda: MemoryLimit(4 << 30, "cgroup memory.max"))
    state, why = make(tmp_path).status("c")
    assert state == "stale" and "3.0 GiB they need as set is there now (4.0 GiB, cgroup memory.max)" in why
    capsys.readouterr()
    make(tmp_path).run(["c"])
    out = capsys.readouterr().out
    assert "[a] up to date" in out and "[b] up to date" in out and "[c] c done" in out
    assert (tmp_path / "out" / "c_runs").read_text() == "2"
