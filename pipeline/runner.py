"""Runs stages in order, skipping those whose cache key matches their last complete output.

On-disk protocol, under a scene's output root:
    <stage>/manifest.json    a complete output; the manifest is written last, so its presence means complete
    .work/<stage>/           the output being written by a run in progress (wiped at the start of each run)
    .resume/<stage>/         checkpoints a stage may resume from when re-run with the same key
    .trash/<stage>/          the previous complete output during the swap; restored if a run dies mid-swap
Files in a stage's folder that it did not write (the user's) are linked into its new output before the swap.
A stage's key hashes its upstream manifests, its resolved settings, its code (every project module its work and its
declaration import, see `pipeline.stage.code_hash`) and (for stages that read the input folder) a fingerprint of the input. Killing the process at any moment leaves the last complete output.
"""
from __future__ import annotations

import fcntl
import hashlib
import json
import os
import shutil
import time
import uuid
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterator

from pipeline import config
from pipeline.disk import (carry_files, damaged_file, folder_bytes, foreign_files, output_files, write_failure,
                           write_failure_line)
from stages.common.json_files import write_json
from stages.common.text import text_name
from stages.capture.photos import scene_source
from pipeline.report import Reporter
from pipeline.stage import StageContext, StageGraph
from plenoxels.core.errors import UserError
from plenoxels.core.memory import memory_limit, release_freed
from stages.common.layout import MANIFEST, MEMORY_AS_SET, RESUME, TRASH, WORK, scene_json


@dataclass
class Plan:
    """Everything that decides a stage's key, computed from what is on disk now."""
    name: str
    settings: Any
    settings_dict: dict
    upstream_keys: dict[str, str]
    code: str
    fingerprint: Any
    scene_type: str | None

    @property
    def key(self) -> str:
        blob = json.dumps({"stage": self.name, "settings": self.settings_dict, "upstream": self.upstream_keys,
                           "code": self.code, "input": self.fingerprint}, sort_keys=True, default=str)
        return hashlib.sha256(blob.encode()).hexdigest()[:20]


def read_manifest(folder: Path) -> dict | None:
    try:
        return json.loads((folder / MANIFEST).read_text())
    except (FileNotFoundError, json.JSONDecodeError):
        return None


def manifest_digest(manifest: dict) -> str:
    return hashlib.sha256(json.dumps(manifest, sort_keys=True).encode()).hexdigest()[:20]


def memory_now_there(manifest: dict) -> str | None:
    """Why an output made with its settings lowered to fit in the memory its run had is out of date, where it is: the
    memory its settings as set need is there now (the summary's MEMORY_AS_SET). A lesser output is not kept where the
    whole one can be made."""
    need = manifest.get("summary", {}).get(MEMORY_AS_SET)
    if not need:
        return None
    limit = memory_limit()
    if limit.bytes < need:
        return None
    return (f"it lowered its settings to fit in memory, and the {need / 2**30:.1f} GiB they need as set is there now "
            f"({limit.bytes / 2**30:.1f} GiB, {limit.source})")


class Pipeline:
    def __init__(self, scene: Path, out: Path, preset: str = "default", overrides: list[str] | None = None,
                 reporter: Reporter | None = None, graph: StageGraph = StageGraph()):
        self.scene = scene_source(scene.resolve())
        self.out = out.resolve()
        if text_name(str(self.out)) != str(self.out):  # COLMAP and OpenCV take paths as UTF-8 text
            raise UserError(f"the output folder {text_name(str(self.out))} has a name that is not UTF-8 text (its "
                            "bytes are shown as %XX); give another with --out")
        self.report = reporter or Reporter()
        self.graph = graph
        self.preset = preset
        self.layers = [config.load_preset(preset)]
        self.overrides = config.parse_overrides(overrides or [])
        unknown = set(self.overrides) - set(graph.order)
        if unknown:
            raise UserError(f"unknown settings section '{sorted(unknown)[0]}'; sections are: {', '.join(graph.order)}")

    # ---- keys and status -------------------------------------------------------------------------------
    def scene_type(self) -> str | None:
        try:
            return json.loads(scene_json(self.out).read_text())["type"]
        except (FileNotFoundError, KeyError, json.JSONDecodeError):
            return None

    def plan(self, name: str) -> Plan:
        declared = self.graph.declaration(name)
        scene_type = self.scene_type() if "normalize" in self.graph.upstream(name) else None
        values = config.merge(*self.layers, config.load_scene_type_overlay(scene_type, self.preset),
                              self.overrides).get(name, {})
        settings = config.build(declared.Settings, name, values)
        upstream_keys = {}
        for dep in declared.DEPENDS:
            manifest = read_manifest(self.out / dep)
            upstream_keys[dep] = manifest_digest(manifest) if manifest else "missing"
        fingerprint = declared.fingerprint(self.scene) if hasattr(declared, "fingerprint") else None
        return Plan(name, settings, config.to_dict(settings), upstream_keys, self.graph.code_hash(name), fingerprint,
                    scene_type)

    def status(self, name: str) -> tuple[str, str]:
        """('done' | 'stale' | 'missing', why)."""
        manifest = read_manifest(self.out / name)
        if manifest is None:
            return "missing", "never completed"
        plan = self.plan(name)
        if manifest.get("key") == plan.key:
            if damaged := damaged_file(self.out / name, manifest):
                return "stale", f"{damaged} changed or was damaged since it was written"
            if lowered := memory_now_there(manifest):
                return "stale", lowered
            # Its own key still matches, but a stage it needs will re-run first and so rebuild it too.
            rerun = [dep for dep in self.graph.declaration(name).DEPENDS if self.status(dep)[0] != "done"]
            if rerun:
                return "stale", f"{rerun[0]} will re-run"
            return "done", f"completed {manifest.get('finished', '?')}"
        reasons = [f"{dep} changed" for dep, k in plan.upstream_keys.items() if manifest.get("upstream", {}).get(dep) != k]
        changed = sorted(k for k in set(plan.settings_dict) | set(manifest.get("settings", {}))
                         if plan.settings_dict.get(k) != manifest.get("settings", {}).get(k))
        if changed:
            reasons.append("settings changed: " + ", ".join(changed))
        if manifest.get("code") != plan.code:
            reasons.append("code changed")
        if manifest.get("input") != json.loads(json.dumps(plan.fingerprint, default=str)):
            reasons.append("input photos changed")
        return "stale", "; ".join(reasons) or "key changed"

    # ---- running -----------------------------------------------------------------------------------------
    def run(self, targets: list[str], force: set[str] = frozenset()) -> dict[str, dict]:
        """Runs each target and whatever it needs, in order; returns the manifests of the targets."""
        wanted = set(targets)
        for t in targets:
            wanted.update(self.graph.upstream(t))
        self.out.mkdir(parents=True, exist_ok=True)
        results = {}
        with self._lock():
            self._recover()
            self._check_scene()
            for name in self.graph.order:
                if name in wanted:
                    results[name] = self._run_one(name, force=name in force)
                    release_freed()  # what one stage freed is not charged to the next (plenoxels/core/memory.py)
        return {t: results[t] for t in targets}

    def _run_one(self, name: str, force: bool) -> dict:
        plan = self.plan(name)
        final = self.out / name
        manifest = read_manifest(final)
        if manifest and manifest.get("key") == plan.key and not force:
            damaged = damaged_file(final, manifest)
            lowered = memory_now_there(manifest) if damaged is None else None
            if damaged is None and lowered is None:
                self.report.summary(name, f"up to date, skipped ({manifest['summary']['line']})")
                return manifest
            self.report.info(f"{damaged} changed or was damaged since the {name} stage wrote it: running {name} again"
                             if damaged else f"{name}: {lowered}: running it again")

        module = self.graph.load(name)
        work = self.out / WORK / name
        try:
            return self._write_output(name, plan, module, work, final, force)
        except (OSError, RuntimeError) as e:
            code = write_failure(e, self.out)
            if code is None:
                raise
            written = folder_bytes(work)
            shutil.rmtree(work, ignore_errors=True)  # what it had written is of no use, and the space is needed
            raise UserError(write_failure_line(name, e, code, self.out, written, folder_bytes(final))) from None

    def _write_output(self, name: str, plan: Plan, module, work: Path, final: Path, force: bool) -> dict:
        """Runs the stage into its work folder, records what it wrote and swaps it into place."""
        scratch = self.out / RESUME / name
        shutil.rmtree(work, ignore_errors=True)
        work.mkdir(parents=True)
        if (scratch / "KEY").is_file() and (scratch / "KEY").read_text() != plan.key or force:
            shutil.rmtree(scratch, ignore_errors=True)
        scratch.mkdir(parents=True, exist_ok=True)
        (scratch / "KEY").write_text(plan.key)

        ctx = StageContext(scene=self.scene, out=self.out, work=work, scratch=scratch, settings=plan.settings,
                           upstream={d: self.out / d for d in self.graph.declaration(name).DEPENDS},
                           scene_type=plan.scene_type, report=self.report)
        self.report.info(f"{name}: running")
        started = time.monotonic()
        summary = module.run(ctx)
        if not isinstance(summary, dict) or "line" not in summary:
            raise TypeError(f"stage {name} must return a summary dict with a 'line'")
        manifest = {
            # A fresh id per run, so downstream keys change whenever this output is rebuilt, even with the same key.
            "stage": name, "run_id": uuid.uuid4().hex, "key": plan.key, "upstream": plan.upstream_keys, "settings": plan.settings_dict,
            "code": plan.code, "input": plan.fingerprint, "scene": str(self.scene), "scene_type": plan.scene_type,
            "started": time.strftime("%Y-%m-%dT%H:%M:%S", time.localtime(started)),
            "finished": time.strftime("%Y-%m-%dT%H:%M:%S"), "seconds": round(time.monotonic() - started, 2),
            "summary": summary, "files": output_files(work),
        }
        write_json(work / MANIFEST, manifest)
        # Files in the old folder the stage did not write are the user's: they go on in the new one.
        kept = carry_files(foreign_files(final), final, work)
        if kept:
            self.report.warn(f"{name}/ held {len(kept)} file(s) this tool did not write; kept in the new {name}/: "
                             f"{', '.join(kept[:4])}{' and more' if len(kept) > 4 else ''}")
        self._swap_into_place(work, final)
        shutil.rmtree(scratch, ignore_errors=True)
        self.report.summary(name, summary["line"])
        return manifest

    def _swap_into_place(self, work: Path, final: Path) -> None:
        trash = self.out / TRASH / final.name
        shutil.rmtree(trash, ignore_errors=True)
        trash.parent.mkdir(exist_ok=True)
        if final.exists():
            os.replace(final, trash)
        os.replace(work, final)
        shutil.rmtree(trash, ignore_errors=True)

    def _check_scene(self) -> None:
        """Stops before anything is replaced where the output folder holds another capture's outputs (its first stage
        names a scene still there, not this one): a second scene of the same folder name would write over the first's
        fit. A scene moved or renamed since goes on."""
        first = read_manifest(self.out / self.graph.order[0])
        before = Path(first["scene"]) if first and first.get("scene") else None
        if before is not None and before != self.scene and before.exists():
            raise UserError(f"{self.out} holds the outputs of another scene ({before}); give this one its own output "
                            "folder (--out, or out= with make), or delete that folder to use it for this one")

    def _recover(self) -> None:
        """Undo a swap that was cut off between its two renames."""
        trash_root = self.out / TRASH
        for trash in trash_root.glob("*") if trash_root.is_dir() else []:
            final = self.out / trash.name
            if not final.exists():  # the output it held, or a folder of the user's files, goes back in place
                os.replace(trash, final)
            else:
                shutil.rmtree(trash, ignore_errors=True)

    @contextmanager
    def _lock(self) -> Iterator[None]:
        with open(self.out / ".lock", "w") as handle:
            try:
                fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                raise UserError(f"another run is using {self.out}; wait for it to finish or use a different --out") from None
            yield


