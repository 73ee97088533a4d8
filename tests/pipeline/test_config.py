"""Settings help lives once, beside each field; `settings` prints it; the `voxfield` console script runs the CLI."""
import subprocess
import sys
import tomllib
from dataclasses import dataclass, field, fields
from pathlib import Path

import pytest

from pipeline import config
from pipeline.stage import STAGE_ORDER, StageGraph
from plenoxels.core.errors import UserError
from stages.settings.fit import Settings as FitSettings
from prerequisites import missing

REPO = Path(__file__).resolve().parents[2]


@dataclass
class Base:
    size: int = 4
    """Cells per side."""


@dataclass
class Toy(Base):
    rates: list[float] = field(default_factory=lambda: [0.1, 0.2])
    """Learning rate per level,
    one per entry."""
    mode: str = "auto"
    quiet: bool = False  # a comment is not help
    """Print nothing."""


def test_field_help_reads_attribute_docstrings_including_inherited_ones():
    assert config.field_help(Toy) == {"size": "Cells per side.", "rates": "Learning rate per level, one per entry.",
                                      "quiet": "Print nothing."}


def test_describe_gives_type_default_preset_value_and_help():
    infos = {info.name: info for info in config.describe(Toy, "toy")}
    assert infos["rates"].default == [0.1, 0.2] and infos["rates"].type == "a list of float"
    assert infos["mode"].help is None and infos["size"].preset_value == 4


@pytest.mark.parametrize("stage", STAGE_ORDER)
def test_every_setting_of_every_stage_has_one_line_of_help(stage):
    settings = StageGraph().declaration(stage).Settings
    helps = config.field_help(settings)
    missing = [f.name for f in fields(settings) if not helps.get(f.name)]
    assert missing == [], f"{stage}.Settings fields without a help line (a docstring on the next line): {missing}"


def test_settings_command_prints_every_stage_with_help_and_the_presets_values():
    result = subprocess.run([sys.executable, "-m", "pipeline", "settings", "--preset", "fast"],
                            capture_output=True, text=True, cwd=REPO)
    assert result.returncode == 0, result.stderr
    for stage in STAGE_ORDER:
        assert f"\n{stage}:\n" in f"\n{result.stdout}"
    assert "ingest.max_side (int) = 960; preset fast: 640" in result.stdout
    help_line = config.field_help(StageGraph().declaration("ingest").Settings)["max_side"]
    assert help_line in result.stdout

    one = subprocess.run([sys.executable, "-m", "pipeline", "settings", "ingest"], capture_output=True, text=True, cwd=REPO)
    assert one.returncode == 0 and one.stdout.startswith("ingest:") and "fit." not in one.stdout


def test_voxfield_console_script_runs_the_cli():
    scripts = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]["scripts"]
    assert scripts["voxfield"] == "pipeline.cli:main"
    installed = Path(sys.executable).parent / "voxfield"
    if not installed.exists():
        missing("voxfield is not installed in this environment yet: make install")
    result = subprocess.run([str(installed), "--help"], capture_output=True, text=True, cwd=REPO)
    assert result.returncode == 0 and result.stdout.startswith("usage: voxfield") and "settings" in result.stdout


@pytest.fixture
def configs(tmp_path, monkeypatch):
    """A configs/ folder of two presets and an object overlay with a section for one of them."""
    (tmp_path / "scene_types").mkdir()
    (tmp_path / "fast.yaml").write_text("fit:\n  resolutions: [64, 128]\n  steps: [100, 400]\n  sh_degree: 1\n")
    (tmp_path / "default.yaml").write_text("fit:\n  resolutions: [64, 128]\n")
    (tmp_path / "scene_types" / "object.yaml").write_text(
        "fit:\n  tv_density: 1.0e-9\npresets:\n  default:\n    fit:\n      error_share: 0.5\n      steps: [200, 700]\n")
    monkeypatch.setattr(config, "CONFIG_DIR", tmp_path)
    return tmp_path


def test_a_scene_types_preset_section_applies_at_that_preset_only(configs):
    at_default = config.load_scene_type_overlay("object", "default")
    assert at_default == {"fit": {"tv_density": 1.0e-9, "error_share": 0.5, "steps": [200, 700]}}
    assert config.load_scene_type_overlay("object", "fast") == {"fit": {"tv_density": 1.0e-9}}
    assert config.load_scene_type_overlay("forward", "default") == {}

    shown = {info.name: info.scene_types for info in config.describe(FitSettings, "fit", "default")}
    assert shown["error_share"] == {"object": 0.5} and shown["tv_density"] == {"object": 1.0e-9}
    assert {info.name: info.scene_types for info in config.describe(FitSettings, "fit", "fast")}["error_share"] == {}


def test_a_pipeline_plans_a_stage_with_its_scene_types_section_for_its_preset(configs, tmp_path):
    from pipeline.runner import Pipeline
    from stages.common.layout import scene_json

    out = tmp_path / "out"
    scene_json(out).parent.mkdir(parents=True)
    scene_json(out).write_text('{"type": "object"}')
    fit = {preset: Pipeline(tmp_path, out, preset=preset).plan("fit").settings for preset in ("fast", "default")}
    assert (fit["default"].error_share, fit["default"].steps, fit["default"].tv_density) == (0.5, [200, 700], 1.0e-9)
    assert (fit["fast"].error_share, fit["fast"].steps, fit["fast"].sh_degree) == (0.0, [100, 400], 1)
    overridden = Pipeline(tmp_path, out, preset="default", overrides=["fit.error_share=0"]).plan("fit").settings
    assert overridden.error_share == 0.0 and overridden.steps == [200, 700]


def test_a_scene_types_section_for_no_preset_is_a_one_line_error(configs):
    (configs / "scene_types" / "object.yaml").write_text("presets:\n  defualt:\n    fit:\n      error_share: 0.5\n")
    with pytest.raises(UserError, match=r"presets.defualt names no preset; presets are: default, fast"):
        config.load_scene_type_overlay("object", "default")
    (configs / "scene_types" / "object.yaml").write_text("presets:\n  default:\n    error_share: 0.5\n")
    with pytest.raises(UserError, match=r"presets.default must map stage names to sections"):
        config.load_scene_type_overlay("object", "fast")


@pytest.mark.parametrize("preset", config.preset_names())
def test_every_preset_builds_every_stage_for_every_scene_type(preset):
    kinds = [None] + sorted(p.stem for p in (config.CONFIG_DIR / "scene_types").glob("*.yaml"))
    for kind in kinds:
        values = config.merge(config.load_preset(preset), config.load_scene_type_overlay(kind, preset))
        for stage in STAGE_ORDER:
            config.build(StageGraph().declaration(stage).Settings, stage, values.get(stage, {}))
