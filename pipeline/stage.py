"""What a stage is, and what it is handed when it runs.

A stage is a module in `stages/` that defines:
    NAME: str                      the stage's name and the folder it writes under the output
    DEPENDS: tuple[str, ...]       the stages whose outputs it reads
    VERSION: int                   bump when the output format changes without a code change being visible
    CODE: tuple[str, ...]          extra repo-relative paths whose source is part of its cache key (its own module always is)
    Settings                       a dataclass of its settings (defaults = the `default` preset)
    run(ctx: StageContext) -> dict the work; writes only into ctx.work; returns its summary, which must hold
                                   "line": one sentence a person can act on
and optionally `fingerprint(scene: Path) -> object`, for stages that read the user's input folder directly, so that
changed photos change the key.
"""
from __future__ import annotations

import hashlib
import importlib
import json
from dataclasses import dataclass
from pathlib import Path
from types import ModuleType
from typing import Any

from pipeline.report import Reporter

REPO_ROOT = Path(__file__).resolve().parent.parent

# The stage graph, in execution order. Each stage's DEPENDS names earlier entries only.
STAGE_ORDER = ("ingest", "poses", "normalize", "fit", "evaluate", "export")


@dataclass
class StageContext:
    scene: Path                    # the user's input: a folder of photos or a video file (read-only)
    out: Path                      # the scene's output root, out/<scene-name>
    work: Path                     # this run's temporary output folder; renamed to out/<NAME> on success
    scratch: Path                  # survives an interrupted run with the same cache key (checkpoints); removed on success
    settings: Any                  # the stage's resolved Settings
    upstream: dict[str, Path]      # name -> the complete output folder of each stage in DEPENDS
    scene_type: str | None         # 'object' | 'forward' | 'unbounded' once normalize has run, else None
    report: Reporter

    def upstream_manifest(self, name: str) -> dict:
        return json.loads((self.upstream[name] / "manifest.json").read_text())


@dataclass(frozen=True)
class StageGraph:
    """Where the stage modules live and the order they run in (tests use a graph of tiny stages)."""
    package: str = "stages"
    order: tuple[str, ...] = STAGE_ORDER

    def load(self, name: str) -> ModuleType:
        return importlib.import_module(f"{self.package}.{name}")

    def upstream(self, name: str) -> list[str]:
        """All stages `name` needs, transitively, in execution order (not including itself)."""
        needed: set[str] = set()
        pending = list(self.load(name).DEPENDS)
        while pending:
            dep = pending.pop()
            if dep not in needed:
                needed.add(dep)
                pending.extend(self.load(dep).DEPENDS)
        return [s for s in self.order if s in needed]


def code_hash(module: ModuleType) -> str:
    """Hash of the stage's own source plus the sources it declares in CODE."""
    digest = hashlib.sha256()
    paths = [Path(module.__file__)]
    for rel in getattr(module, "CODE", ()):
        p = REPO_ROOT / rel
        paths.extend(sorted(f for f in p.rglob("*") if f.suffix in {".py", ".h", ".cpp", ".cu", ".yaml"}) if p.is_dir() else [p])
    for p in paths:
        digest.update(p.name.encode())
        digest.update(p.read_bytes())
    digest.update(str(getattr(module, "VERSION", 0)).encode())
    return digest.hexdigest()[:16]
