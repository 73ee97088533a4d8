"""The stage runner: cache hits, misses and invalidation, atomic outputs under SIGKILL, resume, settings, CLI errors."""
import json
import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest

from pipeline import config
from pipeline.report import Reporter
from pipeline.runner import Pipeline
from pipeline.stage import StageGraph
from plenoxels.core.errors import UserError

REPO = Path(__file__).resolve().parents[2]

# Three tiny stages: a -> b -> c. `a` writes `files` files slowly (so a test can kill it mid-write) and keeps a
# checkpoint in scratch so a re-run can resume.
STAGE_A = '''
from dataclasses import dataclass
import time
NAME, DEPENDS, VERSION = "a", (), 1
@dataclass
class Settings:
    value: int = 1
    files: int = 3
    delay: float = 0.0
def run(ctx):
    done = int((ctx.scratch / "progress").read_text()) if (ctx.scratch / "progress").exists() else 0
    resumed_from = done
    for i in range(done, ctx.settings.files):
        (ctx.work / f"part{i}.txt").write_text(str(ctx.settings.value))
        time.sleep(ctx.settings.delay)
        (ctx.scratch / "progress").write_text(str(i + 1))
    for i in range(resumed_from):
        (ctx.work / f"part{i}.txt").write_text(str(ctx.settings.value))
    return {"line": f"value {ctx.settings.value}", "resumed_from": resumed_from}
'''
STAGE_B = '''
from dataclasses import dataclass
NAME, DEPENDS, VERSION = "b", ("a",), 1
@dataclass
class Settings:
    scale: float = 2.0
def run(ctx):
    value = int((ctx.upstream["a"] / "part0.txt").read_text())
    (ctx.work / "out.txt").write_text(str(value * ctx.settings.scale))
    return {"line": "b done"}
'''
STAGE_C = '''
from dataclasses import dataclass
NAME, DEPENDS, VERSION = "c", ("b",), 1
@dataclass
class Settings:
    label: str = "x"
def run(ctx):
    (ctx.work / "c.txt").write_text((ctx.upstream["b"] / "out.txt").read_text() + ctx.settings.label)
    return {"line": "c done"}
'''


@pytest.fixture
def fake_graph(tmp_path, monkeypatch):
    package = tmp_path / "pkg" / "fakestages"
    package.mkdir(parents=True)
    (package / "__init__.py").write_text("")
    for name, source in (("a", STAGE_A), ("b", STAGE_B), ("c", STAGE_C)):
        (package / f"{name}.py").write_text(textwrap.dedent(source))
    monkeypatch.syspath_prepend(str(tmp_path / "pkg"))
    for mod in [m for m in sys.modules if m.startswith("fakestages")]:
        del sys.modules[mod]
    return StageGraph(package="fakestages", order=("a", "b", "c"), declarations=None)


def make(graph, tmp_path, overrides=()):
    scene = tmp_path / "scene"
    scene.mkdir(exist_ok=True)
    return Pipeline(scene, tmp_path / "out", overrides=list(overrides), reporter=Reporter(quiet=True), graph=graph)


def test_second_run_skips_everything(fake_graph, tmp_path, capsys):
    make(fake_graph, tmp_path).run(["c"])
    first = {s: json.loads((tmp_path / "out" / s / "manifest.json").read_text())["finished"] for s in "abc"}
    capsys.readouterr()
    make(fake_graph, tmp_path).run(["c"])
    out = capsys.readouterr().out
    assert out.count("up to date, skipped") == 3
    assert {s: json.loads((tmp_path / "out" / s / "manifest.json").read_text())["finished"] for s in "abc"} == first


def test_changing_a_setting_reruns_that_stage_and_what_follows(fake_graph, tmp_path, capsys):
    make(fake_graph, tmp_path).run(["c"])
    capsys.readouterr()
    pipe = make(fake_graph, tmp_path, ["b.scale=3"])
    assert pipe.status("a")[0] == "done"
    assert pipe.status("b") == ("stale", "settings changed: scale")
    pipe.run(["c"])
    out = capsys.readouterr().out
    assert "[a] up to date" in out and "[b] b done" in out and "[c] c done" in out
    assert (tmp_path / "out" / "c" / "c.txt").read_text() == "3.0x"


def test_force_reruns_the_stage_and_invalidates_downstream(fake_graph, tmp_path, capsys):
    make(fake_graph, tmp_path).run(["c"])
    capsys.readouterr()
    make(fake_graph, tmp_path).run(["c"], force={"b"})
    out = capsys.readouterr().out
    assert "[a] up to date" in out and "[b] b done" in out and "[c] c done" in out


def test_one_stage_runs_only_what_it_needs(fake_graph, tmp_path):
    make(fake_graph, tmp_path).run(["b"])
    assert (tmp_path / "out" / "b" / "manifest.json").exists()
    assert not (tmp_path / "out" / "c").exists()
    assert make(fake_graph, tmp_path).status("c")[0] == "missing"


def test_manifest_records_inputs_settings_key_and_timing(fake_graph, tmp_path):
    make(fake_graph, tmp_path, ["a.value=7"]).run(["b"])
    manifest = json.loads((tmp_path / "out" / "b" / "manifest.json").read_text())
    upstream = json.loads((tmp_path / "out" / "a" / "manifest.json").read_text())
    assert manifest["settings"] == {"scale": 2.0}
    assert upstream["settings"]["value"] == 7
    assert set(manifest["upstream"]) == {"a"} and manifest["upstream"]["a"] != "missing"
    assert manifest["seconds"] >= 0 and len(manifest["key"]) == 20


def _run_in_subprocess(tmp_path, overrides):
    script = textwrap.dedent(f'''
        import sys
        sys.path[:0] = [{str(tmp_path / "pkg")!r}, {str(REPO)!r}]
        from pathlib import Path
        from pipeline.runner import Pipeline
        from pipeline.report import Reporter
        from pipeline.stage import StageGraph
        Pipeline(Path({str(tmp_path / "scene")!r}), Path({str(tmp_path / "out")!r}), overrides={overrides!r},
                 reporter=Reporter(quiet=True), graph=StageGraph("fakestages", ("a", "b", "c"), None)).run(["a"])
    ''')
    return subprocess.Popen([sys.executable, "-c", script], stdout=subprocess.PIPE, stderr=subprocess.PIPE)


def _kill_when(path_predicate, proc, timeout=30.0):
    deadline = time.time() + timeout
    while not path_predicate():
        assert proc.poll() is None, proc.stderr.read().decode()
        assert time.time() < deadline, "stage never started writing"
        time.sleep(0.02)
    proc.send_signal(signal.SIGKILL)
    proc.wait()


def test_sigkill_mid_write_keeps_last_complete_output_and_resumes(fake_graph, tmp_path):
    make(fake_graph, tmp_path, ["a.value=1", "a.files=3"]).run(["a"])
    out = tmp_path / "out"
    overrides = ["a.value=2", "a.files=6", "a.delay=0.3"]
    proc = _run_in_subprocess(tmp_path, overrides)
    _kill_when(lambda: (out / ".work" / "a" / "part2.txt").exists(), proc)

    # The previous complete output is untouched, and the half-written one is not mistaken for it.
    assert sorted(p.name for p in (out / "a").iterdir()) == ["manifest.json", "part0.txt", "part1.txt", "part2.txt"]
    assert (out / "a" / "part0.txt").read_text() == "1"
    pipe = make(fake_graph, tmp_path, overrides)
    assert pipe.status("a")[0] == "stale"

    # The re-run resumes from the checkpoint the killed run left, then swaps in a complete output.
    manifest = pipe.run(["a"])["a"]
    assert manifest["summary"]["resumed_from"] >= 2
    assert sorted(p.name for p in (out / "a").iterdir() if p.suffix == ".txt") == [f"part{i}.txt" for i in range(6)]
    assert all((out / "a" / f"part{i}.txt").read_text() == "2" for i in range(6))
    assert not (out / ".resume" / "a").exists()


def test_sigkill_during_first_run_leaves_no_output(fake_graph, tmp_path):
    proc = _run_in_subprocess(tmp_path, ["a.files=5", "a.delay=0.3"])
    out = tmp_path / "out"
    _kill_when(lambda: (out / ".work" / "a" / "part1.txt").exists(), proc)
    assert not (out / "a").exists()
    assert make(fake_graph, tmp_path).status("a") == ("missing", "never completed")


def test_a_swap_cut_off_between_renames_is_recovered(fake_graph, tmp_path):
    make(fake_graph, tmp_path).run(["a"])
    out = tmp_path / "out"
    (out / ".trash").mkdir(exist_ok=True)
    os.replace(out / "a", out / ".trash" / "a")  # the state after the first rename of a swap
    make(fake_graph, tmp_path).run(["a"])
    assert (out / "a" / "manifest.json").exists()
    assert not (out / ".trash" / "a").exists()


def test_files_the_user_put_in_a_stage_folder_outlive_every_rerun(fake_graph, tmp_path, capsys):
    out = tmp_path / "out"
    (out / "a" / "notes").mkdir(parents=True)  # a folder of the user's where a stage's output goes
    (out / "a" / "notes" / "plan.txt").write_text("mine")
    (out / "a" / "part0.txt").write_text("also mine")
    make(fake_graph, tmp_path).run(["b"])
    assert (out / "a" / "notes" / "plan.txt").read_text() == "mine"
    assert (out / "a" / "part0.kept.txt").read_text() == "also mine" and (out / "a" / "part0.txt").read_text() == "1"
    assert "a/ held 2 file(s) this tool did not write" in capsys.readouterr().err

    (out / "b" / "scene.blend").write_text("a Blender scene")  # saved beside a complete output
    make(fake_graph, tmp_path, ["b.scale=3"]).run(["b"])
    assert (out / "b" / "scene.blend").read_text() == "a Blender scene" and (out / "b" / "out.txt").read_text() == "3.0"
    assert not (out / "b" / "scene.kept.blend").exists()

    # A swap cut off between its renames, the user's files in the old folder: they go back, and on.
    (out / ".trash").mkdir(exist_ok=True)
    os.replace(out / "a", out / ".trash" / "a")
    (out / ".trash" / "a" / "manifest.json").unlink()
    make(fake_graph, tmp_path).run(["a"])
    assert (out / "a" / "notes" / "plan.txt").read_text() == "mine" and (out / "a" / "manifest.json").exists()
    kept = {p.name: p.read_text() for p in (out / "a").glob("part0.*")}
    assert kept == {"part0.txt": "1", "part0.kept.txt": "also mine", "part0.kept2.txt": "1"}


def test_another_scene_of_the_same_name_never_writes_over_a_scenes_outputs(fake_graph, tmp_path):
    make(fake_graph, tmp_path).run(["b"])
    before = {s: json.loads((tmp_path / "out" / s / "manifest.json").read_text())["run_id"] for s in "ab"}
    other = tmp_path / "elsewhere" / "scene"
    other.mkdir(parents=True)
    pipe = Pipeline(other, tmp_path / "out", reporter=Reporter(quiet=True), graph=fake_graph)
    with pytest.raises(UserError, match=r"holds the outputs of another scene \(.*scene\); give this one its own"):
        pipe.run(["b"])
    assert {s: json.loads((tmp_path / "out" / s / "manifest.json").read_text())["run_id"] for s in "ab"} == before
    (tmp_path / "scene").rename(tmp_path / "moved")  # the first scene moved away: its outputs are this one's to remake
    assert pipe.run(["b"])["b"]["summary"]["line"] == "b done"


def test_overrides_parse_types():
    assert config.parse_overrides(["fit.a=1", "fit.b=0.5", "x.c=[128, 256]", "x.d=auto", "x.e=true"]) == {
        "fit": {"a": 1, "b": 0.5}, "x": {"c": [128, 256], "d": "auto", "e": True}}
    with pytest.raises(UserError, match="section.key=value"):
        config.parse_overrides(["fit_sh_degree=1"])


def test_word_settings_survive_yaml_reading_them_as_booleans():
    # YAML 1.1 reads no/off/yes/on as booleans; a setting whose allowed values are those words must get the word back.
    from stages.settings.fit import Settings as FitSettings
    from stages.settings.poses import Settings as PosesSettings

    for word in ("no", "yes", "auto"):
        parsed = config.parse_overrides([f"poses.shared_camera={word}"])["poses"]
        assert config.build(PosesSettings, "poses", parsed).shared_camera == word
    for word in ("off", "on"):
        assert config.build(FitSettings, "fit", config.parse_overrides([f"fit.ndc={word}"])["fit"]).ndc == word
    with pytest.raises(UserError, match="bad value False for 'poses.matching'"):
        config.build(PosesSettings, "poses", config.parse_overrides(["poses.matching=no"])["poses"])


def test_settings_validation_names_the_key_and_what_is_allowed(fake_graph, tmp_path):
    from stages.settings.ingest import Settings

    with pytest.raises(UserError, match=r"unknown setting 'ingest.max_sid'; allowed: .*max_side"):
        config.build(Settings, "ingest", {"max_sid": 5})
    with pytest.raises(UserError, match=r"bad value 'big' for 'ingest.max_side': expected int"):
        config.build(Settings, "ingest", {"max_side": "big"})
    with pytest.raises(UserError, match="drop_blurry_fraction must be in"):
        config.build(Settings, "ingest", {"drop_blurry_fraction": 1.5})
    assert config.build(Settings, "ingest", {"drop_blurry_fraction": 0}).drop_blurry_fraction == 0.0
    parsed = config.parse_overrides(["ingest.drop_blurry_fraction=5e-2"])["ingest"]
    assert config.build(Settings, "ingest", parsed).drop_blurry_fraction == 0.05
    with pytest.raises(UserError, match="bad value 'nan'"):
        config.build(Settings, "ingest", {"drop_blurry_fraction": "nan"})
    with pytest.raises(UserError, match="unknown settings section 'fitt'"):
        make(fake_graph, tmp_path, ["fitt.x=1"])


def test_every_preset_resolves_for_every_stage():
    from pipeline.stage import STAGE_ORDER, StageGraph

    graph = StageGraph()
    assert {"fast", "balanced", "default", "quality"} <= set(config.preset_names())
    for preset in config.preset_names():
        layers = config.load_preset(preset)
        for name in STAGE_ORDER:
            config.build(graph.declaration(name).Settings, name, layers.get(name, {}))
    with pytest.raises(UserError, match="unknown preset 'nope'; choose one of: .*fast"):
        config.load_preset("nope")


def test_cli_user_error_is_one_line_without_traceback(tmp_path):
    result = subprocess.run([sys.executable, "-m", "pipeline", "run", str(tmp_path / "missing")],
                            capture_output=True, text=True, cwd=REPO)
    assert result.returncode == 2
    assert result.stderr.strip().count("\n") == 0 and "Traceback" not in result.stderr
    assert "does not exist" in result.stderr

    (tmp_path / "photos").mkdir()
    result = subprocess.run([sys.executable, "-m", "pipeline", "ingest", str(tmp_path / "photos"), "--out",
                             str(tmp_path / "out"), "--set", "ingest.max_side=-3"], capture_output=True, text=True, cwd=REPO)
    assert result.returncode == 2 and "Traceback" not in result.stderr
    assert "ingest.max_side" in result.stderr
