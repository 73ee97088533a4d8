"""The output layout is spelled once (stages/common/layout.py): the Makefile's stage targets and the stage graph read
their order from there, and each stage module declares a name in it."""
import importlib
import subprocess
from pathlib import Path

from pipeline.stage import StageGraph
from stages.common import layout

REPO = Path(__file__).resolve().parents[2]


def test_the_makefile_reads_its_stage_list_from_the_layout():
    database = subprocess.run(["make", "-pn", "-C", str(REPO), "status"], capture_output=True, text=True).stdout
    lines = [line for line in database.splitlines() if line.startswith("STAGES :=")]
    assert lines, "make's database has no STAGES variable"
    assert tuple(lines[0].split(":=", 1)[1].split()) == layout.STAGE_ORDER


def test_the_stage_graph_runs_the_layouts_stages_in_its_order():
    graph = StageGraph()
    assert graph.order == layout.STAGE_ORDER
    for position, name in enumerate(layout.STAGE_ORDER):
        declaration = importlib.import_module(f"stages.settings.{name}")
        assert declaration.NAME == name
        assert all(layout.STAGE_ORDER.index(dep) < position for dep in declaration.DEPENDS)


def test_stage_files_live_in_their_stages_folders(tmp_path):
    assert layout.scene_json(tmp_path) == tmp_path / "normalize" / layout.SCENE_JSON
    assert layout.stage_file(tmp_path, "fit", layout.GRID_PT).parent == tmp_path / "fit"
