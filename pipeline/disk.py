"""A stage's output as the disk holds it: the size and hash of every file it wrote (recorded in its manifest, checked
before the output is trusted again), the files in its folder it did not write (kept when the output is replaced), and
the one line a write that failed for want of space or permission becomes."""
from __future__ import annotations

import errno
import hashlib
import json
import os
import shutil
from pathlib import Path

from stages.common.layout import MANIFEST
from stages.common.text import format_bytes

# Errors a write meets from the disk, not from the program: the user can act on each (free space, raise a quota, make
# the folder writable, check the disk), and running the same command again then goes on.
WRITE_FAILURES = {errno.ENOSPC: "the disk is full", errno.EDQUOT: "the disk quota is used up",
                  errno.EROFS: "the file system is read-only", errno.EIO: "the disk reported an input/output error",
                  errno.EFBIG: "the file grew past what the file system allows",
                  errno.EACCES: "permission denied", errno.EPERM: "permission denied"}
# Libraries that write through C++ (COLMAP, torch's zip writer) raise RuntimeError with the system's words in it.
WRITE_FAILURE_WORDS = {"No space left on device": errno.ENOSPC, "Disk quota exceeded": errno.EDQUOT,
                       "Read-only file system": errno.EROFS}
# Below this much free space, a library's failed write (torch says only "file write failed") is taken for a full disk.
FULL_DISK_BYTES = 1 << 20

_HASHES: dict[tuple[str, int, int], str] = {}


def file_sha256(path: Path) -> str:
    """The file's SHA-256, remembered per path, size and modification time, so `status` and a run hash each file once."""
    stat = path.stat()
    key = (str(path), stat.st_size, stat.st_mtime_ns)
    if key not in _HASHES:
        digest = hashlib.sha256()
        with open(path, "rb") as handle:
            while block := handle.read(1 << 20):
                digest.update(block)
        _HASHES[key] = digest.hexdigest()
    return _HASHES[key]


def output_files(folder: Path) -> dict[str, list]:
    """Every file of a stage's output but its manifest: path under the folder -> [bytes, sha256]."""
    return {path.relative_to(folder).as_posix(): [path.stat().st_size, file_sha256(path)]
            for path in sorted(folder.rglob("*")) if path.is_file() and path.name != MANIFEST}


def foreign_files(folder: Path) -> list[str]:
    """Files (paths under `folder`) in a stage's output folder that the stage did not write: every file of a folder
    with no manifest (one made by hand, or in a folder given as the output), else those its manifest does not record
    (a Blender file saved beside the mesh). A manifest that cannot be read or records no files is of an output the
    stage wrote: none."""
    if not folder.is_dir():
        return []
    recorded: dict = {}
    if (folder / MANIFEST).exists():
        try:
            recorded = json.loads((folder / MANIFEST).read_text()).get("files") or {}
        except (OSError, ValueError, AttributeError):
            recorded = {}
        if not recorded:
            return []
    names = (path.relative_to(folder).as_posix() for path in sorted(folder.rglob("*"))
             if path.is_file() or path.is_symlink())
    return [name for name in names if name != MANIFEST and name not in recorded]


def carry_files(names: list[str], source: Path, target: Path) -> list[str]:
    """Links each file `names` holds under `source` into `target` at the same path, or, where that name is taken, at
    `<stem>.kept<suffix>` (`.kept2`, ...) beside it (a copy where the file system cannot link); returns where each
    went. Linked before the old folder is let go, so a run killed at any moment leaves every one of them somewhere."""
    placed = []
    for name in names:
        destination, tries = target / name, 1
        while destination.exists() or destination.is_symlink():
            mark = "kept" if tries == 1 else f"kept{tries}"
            destination, tries = (target / name).with_name(f"{Path(name).stem}.{mark}{Path(name).suffix}"), tries + 1
        destination.parent.mkdir(parents=True, exist_ok=True)
        origin = source / name
        if origin.is_symlink():
            os.symlink(os.readlink(origin), destination)
        else:
            try:
                os.link(origin, destination)
            except OSError:
                shutil.copy2(origin, destination)
        placed.append(destination.relative_to(target).as_posix())
    return placed


def damaged_file(folder: Path, manifest: dict) -> str | None:
    """The first file the manifest records that is gone, cut short or changed since its stage wrote it (named under
    the output root, e.g. fit/grid.pt), or None. A manifest that records no files is trusted as it is."""
    recorded = manifest.get("files") or {}
    for name, (size, _) in recorded.items():
        path = folder / name
        if not path.is_file() or path.stat().st_size != size:
            return f"{folder.name}/{name}"
    for name, (_, sha256) in recorded.items():
        if file_sha256(folder / name) != sha256:
            return f"{folder.name}/{name}"
    return None


def folder_bytes(folder: Path) -> int:
    return sum(p.stat().st_size for p in folder.rglob("*") if p.is_file()) if folder.is_dir() else 0


def write_failure(error: BaseException, out: Path) -> int | None:
    """The errno of a write the disk refused, from an OSError or a library's RuntimeError that quotes it or that met a
    full disk under `out`; else None."""
    if isinstance(error, OSError) and error.errno in WRITE_FAILURES:
        return error.errno
    if isinstance(error, (OSError, RuntimeError)):
        quoted = next((code for words, code in WRITE_FAILURE_WORDS.items() if words in str(error)), None)
        if quoted is not None:
            return quoted
        if out.exists() and shutil.disk_usage(out).free < FULL_DISK_BYTES:
            return errno.ENOSPC
    return None


def write_failure_line(stage: str, error: BaseException, code: int, out: Path, written: int, previous: int) -> str:
    """One line: which stage, which file, why, how much space it needs, and that the same command goes on from there."""
    where = getattr(error, "filename", None) or out
    free = shutil.disk_usage(out).free if out.exists() else 0
    needs = (f"its last complete output took {format_bytes(previous)}" if previous
             else f"it had written {format_bytes(written)} when it stopped")
    todo = ("make the output folder writable or give another --out" if code in (errno.EROFS, errno.EACCES, errno.EPERM)
            else "check the disk" if code == errno.EIO else "free space there or give another --out")
    return (f"the {stage} stage could not write {where}: {WRITE_FAILURES[code]} ({format_bytes(free)} free; {needs}); "
            f"{todo}, then run the same command again: the stages already complete are kept")


def describe_os_error(error: OSError) -> str:
    """One line for an OSError outside a stage (the run's lock, a render or view command)."""
    what = WRITE_FAILURES.get(error.errno or 0, os.strerror(error.errno) if error.errno else str(error))
    where = f" {error.filename}" if error.filename else ""
    return f"cannot use{where}: {what}; free space, fix the folder's permissions or choose another --out, then run again"
