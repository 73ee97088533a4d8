"""Settings help lives once, beside each field; `settings` prints it; the `voxfield` console script runs the CLI."""
import subprocess
import sys
import tomllib
from dataclasses import dataclass, field, fields
from pathlib import Path

import pytest

from pipeline import config
from pipeline.stage import STAGE_ORDER, StageGraph
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
