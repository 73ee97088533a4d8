"""Hostile inputs: each kind in the fuzz corpus is skipped and named, or stops ingest with one UserError line;
never another exception, never a hang, never a write into the input."""
import hashlib
import json
import os
import signal
from pathlib import Path

import pytest

from fuzz_corpus import EXPECT, KINDS, POSE_KINDS
from pipeline.report import Reporter
from pipeline.runner import Pipeline
from plenoxels.core.errors import UserError

SECONDS_PER_KIND = 30


def snapshot(root: Path) -> dict:
    """Every entry under root (links not followed): its mode, mtime and, for files, a hash of its bytes."""
    root = Path(root)
    entries = [root] if root.is_file() else [root, *root.rglob("*")] if not root.is_symlink() else [root]
    seen = {}
    for path in entries:
        st = os.lstat(path)
        digest = hashlib.sha256(path.read_bytes()).hexdigest() if path.is_file() and not path.is_symlink() else None
        seen[str(path)] = (st.st_mode, st.st_mtime_ns, digest)
    return seen


class Hang(Exception):
    pass


def on_alarm(signum, frame):
    raise Hang()


@pytest.mark.parametrize("kind", sorted(KINDS))
def test_hostile_input(kind, tmp_path):
    source = KINDS[kind](tmp_path / "in")
    before = snapshot(tmp_path / "in")
    expect = EXPECT.get(kind, "keep")
    outcome = None
    old = signal.signal(signal.SIGALRM, on_alarm)
    signal.alarm(SECONDS_PER_KIND)
    try:
        Pipeline(source, tmp_path / "out", reporter=Reporter(quiet=True)).run(["ingest"])
        listing = json.loads((tmp_path / "out" / "ingest" / "images.json").read_text())
        outcome = "skip" if listing["skipped"] else "keep"
    except UserError as e:
        outcome = "stop"
        assert "\n" not in str(e).strip(), f"{kind}: a UserError of more than one line: {e}"
    except Hang:
        pytest.fail(f"{kind}: ingest ran past {SECONDS_PER_KIND} s")
    finally:
        signal.alarm(0)
        signal.signal(signal.SIGALRM, old)
    after = snapshot(tmp_path / "in")
    (tmp_path / "in").chmod(0o755)  # so that pytest can clean the read-only kind away
    assert after == before, f"{kind}: ingest wrote into the input"
    assert outcome == expect, f"{kind}: ingest did {outcome!r} where the user must see {expect!r}"


def test_corpus_has_thirty_kinds():
    assert len(KINDS) >= 30


# A frame that names no photo leaves that photo without a pose: left out and named, as SfM leaves out what it cannot
# place; every other spoiled pose file stops the poses stage.
POSES_LEFT_OUT = {"transforms_no_path": "0000"}


@pytest.mark.parametrize("kind", sorted(POSE_KINDS))
def test_spoiled_pose_file(kind, tmp_path):
    """A pose file that is cut short, holds text or NaN where numbers belong, a matrix that is no rigid pose, or lacks
    what a frame needs stops the poses stage with one line that names the file and the frame (or, for a frame that
    names no photo, poses the others and names the photo left out); never a traceback or a hang, never a write
    beside the photos."""
    scene = POSE_KINDS[kind](tmp_path / "in")
    before = snapshot(scene)
    old = signal.signal(signal.SIGALRM, on_alarm)
    signal.alarm(SECONDS_PER_KIND)
    line, stopped = None, False
    try:
        line = Pipeline(scene / "images", tmp_path / "out", reporter=Reporter(quiet=True)).run(["poses"])["poses"]
        line = line["summary"]["line"]
    except UserError as e:
        line, stopped = str(e).strip(), True
    except Hang:
        pytest.fail(f"{kind}: poses ran past {SECONDS_PER_KIND} s")
    finally:
        signal.alarm(0)
        signal.signal(signal.SIGALRM, old)
    assert snapshot(scene) == before, f"{kind}: the poses stage wrote into the input"
    if kind in POSES_LEFT_OUT:
        assert not stopped and f"no pose: {POSES_LEFT_OUT[kind]}" in line, f"{kind}: {line}"
        return
    assert stopped, f"{kind}: the poses stage took a spoiled pose file: {line}"
    assert "\n" not in line, f"{kind}: a UserError of more than one line: {line}"
    files = ("transforms", "poses_bounds", "sparse", "cameras.xml", "reconstruction.json", "pose/",
             "cameras/", "metadata.json", "_cam.txt", ".xmp", "cameras.csv", "cameras.sfm", "bundle.out",
             "sfm_data.json", "calibrated_camera_parameters")
    assert any(name in line for name in files), \
        f"{kind}: the line does not name the pose file: {line}"
    assert not (tmp_path / "out" / "poses").exists()
