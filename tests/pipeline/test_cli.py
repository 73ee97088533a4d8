"""The command line: a table of commands whose modules load only when they run, so `--help`, `status` and `settings`
import neither torch nor COLMAP; progress in a log is plain lines, not carriage-return redraws."""
import io
import json
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest
import tqdm.std

from pipeline import cli
from pipeline.report import PLAIN_SECONDS, Reporter
from pipeline.stage import STAGE_ORDER

REPO = Path(__file__).resolve().parents[2]
# What the quick commands must not load: the model's torch, COLMAP, the viewer's web server, mesh files, Ray.
HEAVY = ("torch", "pycolmap", "viser", "trimesh", "ray")


def run_cli(argv: list[str], cwd: Path = REPO) -> tuple[subprocess.CompletedProcess, list[str]]:
    """`python -m pipeline ARGV` in a fresh interpreter, and the heavy modules it had loaded when it ended."""
    code = textwrap.dedent(f"""
        import json, runpy, sys
        sys.argv = ["pipeline", *{argv!r}]
        try:
            runpy.run_module("pipeline", run_name="__main__")
        except SystemExit as end:
            code = end.code
        print(json.dumps(sorted(m for m in {HEAVY!r} if m in sys.modules)), file=sys.stderr)
        sys.exit(code)
    """)
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=cwd)
    *_, loaded = result.stderr.strip().splitlines()
    return result, json.loads(loaded)


def test_help_lists_every_command_from_the_table_and_loads_nothing_heavy():
    result, loaded = run_cli(["--help"])
    assert result.returncode == 0, result.stderr
    for name, command in cli.COMMANDS.items():
        assert f"    {name}" in result.stdout and command.help.split()[0] in result.stdout
    assert loaded == [], f"--help loaded {loaded}"


def test_settings_loads_neither_torch_nor_colmap():
    result, loaded = run_cli(["settings", "--preset", "fast"])
    assert result.returncode == 0, result.stderr
    assert all(f"\n{stage}:\n" in f"\n{result.stdout}" for stage in STAGE_ORDER)
    assert "fit.sh_degree (int) = 2; preset fast: 1" in result.stdout
    assert loaded == [], f"settings loaded {loaded}"


def test_status_of_a_finished_scene_loads_neither_torch_nor_colmap(tmp_path):
    """Every stage has an output here, so status computes each stage's key: settings, code and input."""
    photos = tmp_path / "photos"
    photos.mkdir()
    for name in ("a.png", "b.png", "c.png"):
        (photos / name).write_bytes(b"not decoded by status")
    for stage in STAGE_ORDER:
        (tmp_path / "out" / stage).mkdir(parents=True)
        (tmp_path / "out" / stage / "manifest.json").write_text(json.dumps({"key": "old", "settings": {}}))
    result, loaded = run_cli(["status", str(photos), "--out", str(tmp_path / "out")])
    assert result.returncode == 0, result.stderr
    lines = result.stdout.splitlines()
    assert [line.split()[0] for line in lines] == list(STAGE_ORDER)
    assert "settings changed" in lines[0] and "code changed" in lines[0] and "input photos changed" in lines[0]
    assert loaded == [], f"status loaded {loaded}"


@pytest.mark.parametrize("name", list(cli.COMMANDS))
def test_every_command_of_the_table_has_a_module_with_its_arguments(name):
    parser, module = cli.command_parser(name)
    assert callable(module.main) and parser.prog.endswith(f" {name}")
    assert parser.description == cli.COMMANDS[name].help
    with pytest.raises(SystemExit) as end:
        parser.parse_args(["--help"])
    assert end.value.code == 0


def test_every_stage_is_a_command_and_an_unknown_one_is_an_error_naming_them(capsys):
    assert set(STAGE_ORDER) <= set(cli.COMMANDS)
    with pytest.raises(SystemExit) as end:
        cli.main(["fitt"])
    assert end.value.code == 2 and "invalid choice: 'fitt'" in capsys.readouterr().err


def test_a_commands_arguments_are_its_own(tmp_path, capsys):
    with pytest.raises(SystemExit) as end:
        cli.main(["status", str(tmp_path), "--until", "fit"])  # run's option, not status's
    assert end.value.code == 2 and "--until" in capsys.readouterr().err


# ---- progress ------------------------------------------------------------------------------------------------------
def ten_minutes_of_steps(monkeypatch, reporter: Reporter) -> str:
    """What `reporter` writes for 600 steps a second apart (on a clock of the test's own)."""
    clock = [1000.0]
    monkeypatch.setattr(tqdm.std, "time", lambda: clock[0])
    stream = io.StringIO()
    monkeypatch.setattr(sys, "stderr", stream)
    with reporter.bar(total=600, desc="fitting") as bar:
        for _ in range(600):
            clock[0] += 1.0
            bar.update(1)
            bar.set_postfix(loss="0.0012", refresh=False)
    return stream.getvalue()


def test_progress_that_is_not_on_a_terminal_is_a_plain_line_a_few_times_a_minute(monkeypatch):
    text = ten_minutes_of_steps(monkeypatch, Reporter())  # stderr is a StringIO: not a terminal
    lines = text.splitlines()
    assert "\r" not in text and text.endswith("\n")
    assert 600 / PLAIN_SECONDS - 1 <= len(lines) <= 600 / PLAIN_SECONDS + 1, lines
    assert lines[-1].startswith("  fitting: 600/600 (100%)") and "loss=0.0012" in lines[-1]


def test_progress_on_a_terminal_redraws_one_line(monkeypatch):
    text = ten_minutes_of_steps(monkeypatch, Reporter(plain=False))
    assert text.count("\r") > 600 / PLAIN_SECONDS and text.count("\n") <= 1
