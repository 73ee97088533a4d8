"""What a stage is, and what it is handed when it runs.

A stage is declared by a module that defines
    NAME: str                      the stage's name and the folder it writes under the output
    DEPENDS: tuple[str, ...]       the stages whose outputs it reads
    VERSION: int                   bump when the output format changes without a code change being visible
    Settings                       a dataclass of its settings (defaults = the `default` preset)
and optionally `fingerprint(scene: Path) -> object`, for stages that read the user's input folder directly, so that
changed photos change the key; its work is a module that defines
    run(ctx: StageContext) -> dict the work; writes only into ctx.work; returns its summary, which must hold
                                   "line": one sentence a person can act on
For the pipeline's stages the declaration is `stages/settings/<name>.py` and the work `stages/<name>.py`, so that
planning a stage, its cache key, `status` and `settings` import no more than its settings need (no torch, no COLMAP);
a graph without a declarations package finds both in the stage's one module.

A stage's code enters its cache key through `code_hash`: the sources of every project module in the import closure of
its work and of its declaration (found by parsing imports, not listed by hand, and without importing them), plus the
native core's sources when the closure loads it.
"""
from __future__ import annotations

import ast
import hashlib
import importlib
import importlib.util
import json
from dataclasses import dataclass
from pathlib import Path
from types import ModuleType
from typing import Any, Iterator

from pipeline.report import Reporter
from stages.common.layout import MANIFEST, STAGE_ORDER

REPO_ROOT = Path(__file__).resolve().parent.parent

# The stage graph runs in STAGE_ORDER (stages/common/layout.py); each stage's DEPENDS names earlier entries only.


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
        return json.loads((self.upstream[name] / MANIFEST).read_text())


@dataclass(frozen=True)
class StageGraph:
    """Where the stage modules live and the order they run in (tests use a graph of tiny stages)."""
    package: str = "stages"
    order: tuple[str, ...] = STAGE_ORDER
    declarations: str | None = "stages.settings"
    """The package of the stages' declarations (NAME, DEPENDS, VERSION, Settings, fingerprint); None: each stage's
    module in `package` declares itself."""

    def module_name(self, name: str) -> str:
        """The module of the stage's work (its `run`)."""
        return f"{self.package}.{name}"

    def declaration_name(self, name: str) -> str:
        return f"{self.declarations}.{name}" if self.declarations else self.module_name(name)

    def load(self, name: str) -> ModuleType:
        """The stage's work: imported only to run it."""
        return importlib.import_module(self.module_name(name))

    def declaration(self, name: str) -> ModuleType:
        """What the pipeline plans the stage by: its NAME, DEPENDS, VERSION, Settings and fingerprint."""
        return importlib.import_module(self.declaration_name(name))

    def upstream(self, name: str) -> list[str]:
        """All stages `name` needs, transitively, in execution order (not including itself)."""
        needed: set[str] = set()
        pending = list(self.declaration(name).DEPENDS)
        while pending:
            dep = pending.pop()
            if dep not in needed:
                needed.add(dep)
                pending.extend(self.declaration(dep).DEPENDS)
        return [s for s in self.order if s in needed]

    def code_hash(self, name: str) -> str:
        """The stage's code as its cache key sees it (see `code_hash`)."""
        modules = dict.fromkeys([self.module_name(name), self.declaration_name(name)])
        return code_hash(list(modules), self.declaration(name).VERSION)


# Project packages whose modules are followed when computing a stage's import closure; anything else (numpy, torch)
# is a dependency pinned by the install, not project code.
PROJECT_PACKAGES = ("pipeline", "plenoxels", "stages")
# The native core is built from these sources; a module that loads it depends on them as much as on Python code.
NATIVE_MODULES = ("plenoxels.core.native", "plenoxels._C")
NATIVE_SOURCES = REPO_ROOT / "csrc"


def _package_dir(top: str) -> Path | None:
    spec = importlib.util.find_spec(top)
    if spec is None or not spec.submodule_search_locations:
        return None
    return Path(list(spec.submodule_search_locations)[0])


def _module_file(name: str, roots: dict[str, Path]) -> Path | None:
    """The source file of project module `name` (a package's __init__.py), or None if it is not one."""
    top, *rest = name.split(".")
    if top not in roots:
        return None
    base = roots[top].joinpath(*rest)
    for candidate in (base / "__init__.py", base.with_suffix(".py")):
        if candidate.is_file():
            return candidate
    return None


def _statements(tree: ast.AST) -> Iterator[ast.stmt]:
    """Every statement in `tree`, at any depth (in functions, classes, branches, handlers), skipping expressions: an
    import is a statement, and a module's expressions are most of its nodes."""
    pending = [tree]
    while pending:
        node = pending.pop()
        for field in ("body", "orelse", "finalbody", "handlers", "cases"):
            for child in getattr(node, field, ()):
                if isinstance(child, ast.stmt):
                    yield child
                pending.append(child)


def _imported_names(tree: ast.AST, name: str, is_package: bool) -> set[str]:
    """Every module name an import statement in `tree` may load, with each parent package and, for
    `from X import Y`, the submodule X.Y in case Y is one."""
    package = name if is_package else name.rpartition(".")[0]
    found: set[str] = set()
    for node in _statements(tree):
        if isinstance(node, ast.Import):
            targets = [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")[: len(package.split(".")) - node.level + 1]
                stem = ".".join(base + ([node.module] if node.module else []))
            else:
                stem = node.module or ""
            targets = [stem] + [f"{stem}.{alias.name}" for alias in node.names if alias.name != "*"]
        else:
            continue
        for target in targets:
            parts = target.split(".")
            found.update(".".join(parts[: i + 1]) for i in range(len(parts)) if parts[0])
    return found


def import_closure(module_name: str) -> dict[str, Path]:
    """Module name -> source file for `module_name` and every project module it imports, directly or not.
    Imports anywhere in a module count (inside functions too), so the closure errs on the side of too much."""
    tops = set(PROJECT_PACKAGES) | {module_name.split(".")[0]}
    roots = {top: d for top in sorted(tops) if (d := _package_dir(top)) is not None}
    closure: dict[str, Path] = {}
    pending = [module_name]
    while pending:
        name = pending.pop()
        if name in closure:
            continue
        path = _module_file(name, roots)
        if path is None:
            if name in NATIVE_MODULES:
                closure[name] = NATIVE_SOURCES
            continue
        closure[name] = path
        parents = name.split(".")
        pending.extend(".".join(parents[: i + 1]) for i in range(len(parents) - 1))
        pending.extend(_imports_of(name, path))
    return closure


# Parsing is most of the cost of a key and `status` computes many; keyed by content, so an edit is never missed.
_IMPORTS_SEEN: dict[tuple[str, bool, bytes], frozenset[str]] = {}


def _imports_of(name: str, path: Path) -> frozenset[str]:
    source = path.read_bytes()
    is_package = path.name == "__init__.py"
    key = (name, is_package, hashlib.sha256(source).digest())
    if key not in _IMPORTS_SEEN:
        _IMPORTS_SEEN[key] = frozenset(_imported_names(ast.parse(source, filename=str(path)), name, is_package))
    return _IMPORTS_SEEN[key]


def code_hash(module_names: list[str], version: int = 0) -> str:
    """Hash of the sources of `module_names` and every project module they import (see `import_closure`), read from
    their files without importing them, of the native core's sources when one of them loads it, and of the stage's
    VERSION."""
    closure: dict[str, Path] = {}
    for module_name in module_names:
        closure.update(import_closure(module_name))
    if any(name in closure for name in NATIVE_MODULES):
        closure = {name: path for name, path in closure.items() if path != NATIVE_SOURCES}
        for path in sorted(p for p in NATIVE_SOURCES.rglob("*") if p.is_file()):
            closure[f"csrc/{path.relative_to(NATIVE_SOURCES).as_posix()}"] = path
    digest = hashlib.sha256()
    for name in sorted(closure):
        digest.update(name.encode() + b"\0")
        digest.update(closure[name].read_bytes())
    digest.update(str(version).encode())
    return digest.hexdigest()[:16]
