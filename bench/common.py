"""What several benchmark parts share."""
from __future__ import annotations

import json
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from pipeline.report import Reporter
from pipeline.stage import StageContext
from plenoxels.core.files import write_whole


@contextmanager
def fit_context(scene: dict, root: Path, settings, report: Reporter) -> Iterator[StageContext]:
    """The fit stage's context for a scene.json built in memory (a benchmark's own split or scene), without a
    pipeline run: the frames' image paths resolve against `root`, and the fit writes into a temporary folder
    that lives as long as the `with` block."""
    with tempfile.TemporaryDirectory(prefix="bench-fit-") as tmp:
        tmp = Path(tmp)
        for name in ("normalize", "work", "scratch"):
            (tmp / name).mkdir()
        (tmp / "normalize" / "scene.json").write_text(json.dumps(scene))
        yield StageContext(scene=root, out=root, work=tmp / "work", scratch=tmp / "scratch", settings=settings,
                           upstream={"normalize": tmp / "normalize"}, scene_type=scene["type"], report=report)


def fitted(scene: dict, root: Path, settings, quiet: bool = True) -> tuple[dict, float, dict, object]:
    """Runs the fit stage on `scene` (see fit_context) and returns its summary, its wall seconds, its fit.json and the
    fitted model."""
    from plenoxels.core.scene_model import SceneModel
    from stages import fit

    with fit_context(scene, root, settings, Reporter(quiet=quiet)) as ctx:
        started = time.time()
        summary = fit.run(ctx)
        wall = time.time() - started
        return summary, wall, json.loads((ctx.work / "fit.json").read_text()), SceneModel.load(ctx.work)


def recorded() -> str:
    """When and on what code a result is measured: today's date and the commit checked out, with a + when tracked
    files differ from it ('2026-11-26 94122cf')."""
    repo = Path(__file__).resolve().parent.parent

    def git(*args: str) -> str:
        return subprocess.run(["git", *args], cwd=repo, capture_output=True, text=True).stdout.strip()

    changed = git("status", "--porcelain", "--untracked-files=no")
    return f"{time.strftime('%Y-%m-%d')} {git('rev-parse', '--short=7', 'HEAD') or 'unknown'}{'+' if changed else ''}"


def write_runs(path: Path, results: dict) -> None:
    """A results document, its runs one to a line: hundreds of budgeted fits in a few MB (indented, a run's budget
    record alone takes a hundred lines), and a new run one line of the diff."""
    head = json.dumps({key: value for key, value in results.items() if key != "runs"})
    runs = ",\n".join(json.dumps(run) for run in results.get("runs", []))
    text = head[:-1] + (", " if head != "{}" else "") + '"runs": [\n' + runs + "\n]}\n"
    json.loads(text)  # a document that reads back, before it replaces the one on disk
    write_whole(path, lambda tmp: Path(tmp).write_text(text))


def budget_of(record: dict) -> dict:
    """A budgeted fit's plan, re-plans and what it measured of the scene, from its fit.json (of the calibration, its
    cost model and the scale it was timed at again, its points left out), as a run's `budget`; nothing for a fit
    without a budget."""
    if "budget" not in record:
        return {}
    calibration = record["budget"].get("calibration", {})
    return {"budget": {**{k: v for k, v in record["budget"].items() if k != "calibration"},
                       "calibration": {k: calibration.get(k) for k in ("costs", "cached", "slower_now", "when")}}}


def run_child(module: str, spec: dict, what: str) -> dict | None:
    """Runs `python -m <module> --one` with `spec` on its standard input, in the repository, and returns the JSON
    result it prints last; None, after saying `what` failed, when it exits with an error."""
    repo = Path(__file__).resolve().parent.parent
    proc = subprocess.run([sys.executable, "-m", module, "--one"], input=json.dumps(spec), cwd=repo,
                          stdout=subprocess.PIPE, text=True)
    if proc.returncode != 0:
        print(f"  {what}: failed (exit {proc.returncode})", flush=True)
        return None
    return json.loads(proc.stdout.strip().splitlines()[-1])


def run_part(args, one_run, whole_run) -> int:
    """A benchmark part's entry: with --one, one measurement whose spec arrives as JSON on stdin (so each run has
    a process, and a peak memory, of its own) and whose result leaves as JSON on stdout; else the whole part.
    A bad argument or input is a one-line error."""
    from plenoxels.core.errors import UserError

    try:
        if args.one:
            print(json.dumps(one_run(json.loads(sys.stdin.read()))))
            return 0
        return whole_run(args)
    except UserError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2


def fit_overrides(items: list[str]) -> dict:
    """`--set key=value` items (fit settings, `fit.` prefix optional) as a dict of YAML-parsed values."""
    import yaml

    from plenoxels.core.errors import UserError

    overrides = {}
    for item in items:
        key, sep, raw = item.partition("=")
        if not sep:
            raise UserError(f"--set '{item}' must look like key=value (a fit setting, for example sh_degree=1)")
        overrides[key.strip().removeprefix("fit.")] = yaml.safe_load(raw)
    return overrides
