"""Reading a video: its frames kept by the view's motion, the sharpest of each stretch, upright, within any black
bars; and a folder of a video's frames saved one by one, read as the video would be."""
from __future__ import annotations

import math
import tempfile
from pathlib import Path

import cv2
import numpy as np

from plenoxels.core.errors import UserError
from stages.capture.photos import fit_max_side, load_photo, sharpness
from stages.capture.picture import BAR_SAMPLES, paint_over, picture_box, still_overlay
from stages.common.text import text_name

# Video frames are tracked at this size; a stretch ends when fewer than this share of its corners are still followed,
# and its frames past this share of the motion wanted are candidates to keep.
TRACKING_SIDE = 480
TRACKS_KEPT_SHARE = 0.5
CANDIDATE_SHARE = 0.6
# A clip that gives too few frames at the motion set is read again at most VIDEO_RETRIES times, with frames at least
# MIN_MOTION_SHARE of that motion apart (closer, neighbours differ by less than SfM can triangulate from).
VIDEO_RETRIES = 3
MIN_MOTION_SHARE = 0.25
# A folder of more photos than ingest.video_max_frames is looked at for a video's frames saved one by one at this
# many places through it (two photos each): neighbours closer than this share of ingest.video_motion are such frames.
# A walk around ball filmed at 30 frames a second moves 1.2% of the view's diagonal a frame (its 16 s clip, 5.8
# diagonals in all); measured neighbours of photos taken one by one: 4.1% (fox), 14% (cup); ball's frames at 8 a
# second 4.9%.
SEQUENCE_PAIRS = 10
SEQUENCE_MOTION_SHARE = 0.5


def _shift(followed: np.ndarray, start: np.ndarray, shape: tuple[int, ...]) -> float:
    """How far followed corners moved from where they started: the median, as a share of the frame's diagonal."""
    return float(np.median(np.linalg.norm((followed - start).reshape(-1, 2), axis=1))) / float(np.hypot(*shape[:2]))


def _view_motion(first: np.ndarray, second: np.ndarray) -> float:
    """How far the view moved between two grey frames, as a share of their diagonal: the median motion of the first's
    corners followed into the second by optical flow; 1 where fewer than TRACKS_KEPT_SHARE of them can be followed."""
    corners = _corners(first)
    if corners is None or first.shape != second.shape:
        return 1.0
    followed, status, _ = cv2.calcOpticalFlowPyrLK(first, second, corners, None)
    alive = status.ravel() == 1
    if alive.sum() < TRACKS_KEPT_SHARE * len(corners):
        return 1.0
    return _shift(followed[alive], corners[alive], first.shape)


def sequence_step(paths: list[Path], motion: float, max_frames: int, target_frames: int) -> tuple[int, float]:
    """Of a folder's photos in name order: whether they are a video's frames saved one by one (neighbours, at
    SEQUENCE_PAIRS places through the folder, closer than SEQUENCE_MOTION_SHARE of `motion`), and if so, every how many
    to read, as a video is read: frames about `motion` apart, at most `max_frames`, but not fewer than `target_frames`
    for that spacing; 1 for separate photos. Also the neighbours' median motion."""
    moves = []
    for i in np.linspace(0, len(paths) - 2, SEQUENCE_PAIRS).round().astype(int):
        try:
            first, second = (_tracking_grey(cv2.cvtColor(load_photo(paths[j])[0], cv2.COLOR_RGB2BGR))
                             for j in (i, i + 1))
        except Exception:  # an unreadable photo is skipped where it is loaded
            continue
        moves.append(_view_motion(first, second))
    apart = float(np.median(moves)) if moves else 1.0
    if apart >= SEQUENCE_MOTION_SHARE * motion:
        return 1, apart
    spaced = min(round(motion / max(apart, 1e-4)), len(paths) // max(target_frames, 1))
    return max(1, math.ceil(len(paths) / max_frames) if max_frames else 1, spaced), apart


def frame_name(index: int) -> str:
    """A kept frame's name, from its index in the clip."""
    return f"frame_{index:06d}"


def frame_seconds(name: str, fps: float) -> float:
    """How far into its clip a kept frame (by its name) was taken: the middle of its span."""
    return (int(name.removeprefix("frame_")) + 0.5) / fps


def open_video(path: Path) -> cv2.VideoCapture:
    """A video opened for reading, upright (its rotation metadata applied), or one line that says it cannot be. A path
    that is not UTF-8 (a name from another system), which OpenCV cannot take, is opened through a link of a plain name,
    gone once the file is open."""
    try:
        str(path).encode("utf-8")
        capture = cv2.VideoCapture(str(path))
    except UnicodeEncodeError:
        with tempfile.TemporaryDirectory() as folder:
            link = Path(folder) / "video"
            link.symlink_to(path.resolve())
            capture = cv2.VideoCapture(str(link))
    if not capture.isOpened():
        raise UserError(f"cannot read video {text_name(path.name)}; convert it to MP4 (H.264) or extract photos")
    capture.set(cv2.CAP_PROP_ORIENTATION_AUTO, 1)
    return capture


def _tracking_grey(bgr: np.ndarray) -> np.ndarray:
    grey = cv2.cvtColor(bgr, cv2.COLOR_BGR2GRAY)
    scale = TRACKING_SIDE / max(grey.shape)
    return cv2.resize(grey, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA) if scale < 1 else grey


def _corners(grey: np.ndarray, allowed: np.ndarray | None = None) -> np.ndarray | None:
    """Corners to follow, only where `allowed` (a mask of the grey's shape) is non-zero, where given."""
    return cv2.goodFeaturesToTrack(grey, maxCorners=400, qualityLevel=0.01, minDistance=max(4, max(grey.shape) // 60),
                                   mask=allowed)


def clip_samples(path: Path) -> list[np.ndarray]:
    """BAR_SAMPLES grey frames spread over a clip, as it is stored: what black bars and a still overlay are found
    in."""
    capture = open_video(path)
    total = int(capture.get(cv2.CAP_PROP_FRAME_COUNT))
    # Read on, not seeked: a seek decodes from the last key frame, which cost ball's 127-frame clip 2.2 s for 24
    # samples against 0.5 s to decode it all. A clip of unknown length gives its first samples, 10 frames apart.
    step = max(1, total // BAR_SAMPLES) if total > 0 else 10
    greys, index = [], 0
    while len(greys) < BAR_SAMPLES and capture.grab():
        if index % step == 0:
            ok, bgr = capture.retrieve()
            if ok:
                greys.append(cv2.cvtColor(bgr, cv2.COLOR_BGR2GRAY))
        index += 1
    capture.release()
    return greys


def video_frames(path: Path, max_side: int, motion: float, max_per_second: float, report,
                 target_frames: int = 0, crop_bars: bool = True, max_frames: int = 0,
                 paint_overlays: bool = True, samples: list[np.ndarray] | None = None
                 ) -> tuple[list[tuple[str, np.ndarray]], dict]:
    """(name, RGB) of the frames to pose from a video (see frames_by_motion), and what the clip gave: its `seconds`,
    the `motion` the frames were kept at and `total_motion` (diagonals the view moved in all). A clip whose motion
    gives fewer than `target_frames` at `motion` (a short clip, or a camera that moved little) is read again with
    frames closer together, as close as the motion allows for `target_frames` but never below MIN_MOTION_SHARE of
    `motion`, nor more than `max_per_second` a second. A clip that gives more than `max_frames` (0: no limit; a
    long one) is read again keeping every `every`-th frame due, so the frames span the whole clip and memory holds
    no more than that many. With `crop_bars`, black bars along the frame's edges (`picture_box` over `clip_samples`)
    are cropped from every frame before anything else, and the clip's `bars` say what was kept: [x, y, width, height]
    of the frame's [width, height]. With `paint_overlays`, a still overlay on the picture (`still_overlay`: a
    watermark, a caption) is left out of the motion's corners and painted over in each frame kept; the clip's
    `overlay` is its share of the picture. `samples`: the clip's `clip_samples` where they were read already."""
    if samples is None:
        samples = clip_samples(path) if crop_bars or paint_overlays else []
    picture = picture_box(samples) if crop_bars else None
    overlay = still_overlay([g[picture] if picture else g for g in samples]) if paint_overlays else None

    def read(at: float, every: int = 1) -> tuple[list[tuple[str, np.ndarray]], dict]:
        return frames_by_motion(path, max_side, at, max_per_second, report, picture, max_frames if every == 1 else 0,
                                every, overlay)

    kept, clip = read(motion)
    used = motion
    for _ in range(VIDEO_RETRIES):
        if not target_frames or clip["due"] >= target_frames or clip["due"] >= clip["most_frames"]:
            break
        denser = max(motion * MIN_MOTION_SHARE, min(used * 0.7, clip["total_motion"] / target_frames))
        if denser >= used:
            break
        used = denser
        kept, clip = read(used)
    every = 1
    if max_frames and clip["due"] > max_frames:
        every = math.ceil(clip["due"] / max_frames)
        kept, clip = read(used, every)
        if len(kept) > max_frames:  # the second reading's stretches fell a little differently
            kept = [kept[i] for i in np.linspace(0, len(kept) - 1, max_frames).round().astype(int)]
    if overlay is not None:
        kept = [(name, paint_over(rgb, overlay)) for name, rgb in kept]
        clip["overlay"] = round(float(overlay.mean()), 4)
    return kept, {**clip, "motion": used, "every": every, "max_per_second": max_per_second, "crop_bars": crop_bars,
                  "paint_overlays": paint_overlays, "max_frames": max_frames}


def frames_by_motion(path: Path, max_side: int, motion: float, max_per_second: float, report,
                     picture: tuple[slice, slice] | None = None, max_frames: int = 0, keep_every: int = 1,
                     overlay: np.ndarray | None = None) -> tuple[list[tuple[str, np.ndarray]], dict]:
    """(name, RGB) of the frames to pose from a video, upright (its rotation metadata applied), cropped to
    `picture` (rows, columns) where given, downscaled to
    `max_side`, and the clip's `seconds`, `total_motion` and `most_frames` (what `max_per_second` allows). A frame is
    due each time the view has moved by `motion` of the frame's diagonal since the last kept
    frame (the median motion of corners tracked from it by optical flow), or when fewer than half of those corners
    can still be followed, so neighbours keep overlapping however fast or slowly the camera moved; of the frames
    in the last stretch before that point, the sharpest is kept. At most `max_per_second` frames per second of video.
    Of the frames due, every `keep_every`-th is kept (the first included). Past `max_frames` (0: no limit) the frames
    due are only counted, their pixels let go, and none are returned: the clip's `due` says how many there were. No
    corner is followed on `overlay` (a mask of the picture's shape), which does not move with the view."""
    capture = open_video(path)
    fps = capture.get(cv2.CAP_PROP_FPS) or 30.0
    total = int(capture.get(cv2.CAP_PROP_FRAME_COUNT)) or None
    min_gap = max(1, round(fps / max_per_second))
    kept: list[tuple[str, np.ndarray]] = []
    # The sharpest candidate since the stretch began, (sharpness, index, rgb): one frame held, however long the stretch.
    best: tuple[float, int, np.ndarray] | None = None
    previous = points = start = None
    index, last_kept, tracked, due = 0, -min_gap, 0, 0
    total_motion, counted = 0.0, 0.0  # diagonals moved in all: the stretches ended, and the current one so far
    counting = False  # past max_frames: the frames due are counted, and none held

    def allowed(grey: np.ndarray) -> np.ndarray | None:
        """Where corners may be followed in a tracked frame: off the overlay."""
        if overlay is None:
            return None
        return (cv2.resize(overlay.astype(np.uint8), (grey.shape[1], grey.shape[0]), interpolation=cv2.INTER_AREA)
                == 0).astype(np.uint8)

    def keeping() -> bool:
        """Whether the next frame due is kept, so its stretch's candidates need their pixels."""
        return due % keep_every == 0 and not counting

    def keep(frame: tuple[float, int, np.ndarray | None]) -> None:
        nonlocal last_kept, due, counting
        if frame[2] is not None:
            kept.append((frame_name(frame[1]), frame[2]))
            if max_frames and len(kept) > max_frames:
                kept.clear()
                counting = True
        last_kept, due = frame[1], due + 1

    with report.bar(total=total, desc=f"reading {path.name}") as bar:
        while True:
            ok, bgr = capture.read()
            if not ok:
                break
            if picture is not None:
                frame_shape = bgr.shape[:2]
                bgr = np.ascontiguousarray(bgr[picture])
            grey = _tracking_grey(bgr)
            moved, lost = 0.0, False
            if previous is not None and points is not None and len(points):
                followed, status, _ = cv2.calcOpticalFlowPyrLK(previous, grey, points, None)
                alive = status.ravel() == 1
                points, start = followed[alive], start[alive]
                lost = len(points) < TRACKS_KEPT_SHARE * tracked
                if len(points):
                    moved = _shift(points, start, grey.shape)
                    counted = max(counted, moved)
            if previous is None or points is None or not len(points):
                total_motion, counted = total_motion + counted, 0.0
                points = _corners(grey, allowed(grey))
                start, tracked = points, len(points) if points is not None else 0
                if not due:  # the first frame anchors the sequence
                    rgb = fit_max_side(cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB), max_side)
                    keep((sharpness(rgb), index, rgb))
            elif (moved >= CANDIDATE_SHARE * motion or lost) and not keeping():
                best = best or (0.0, index, None)
            elif moved >= CANDIDATE_SHARE * motion or lost:
                rgb = fit_max_side(cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB), max_side)
                score = sharpness(rgb)
                if best is None or score > best[0]:
                    best = (score, index, rgb)
            if (moved >= motion or lost) and best is not None and index - last_kept >= min_gap:
                keep(best)
                best = None
                # Track again from this frame: the next stretch is measured from (about) the frame just kept.
                total_motion, counted = total_motion + counted, 0.0
                points = _corners(grey, allowed(grey))
                start, tracked = points, len(points) if points is not None else 0
            previous = grey
            index += 1
            bar.update()
    if best is not None and best[1] - last_kept >= min_gap:
        keep(best)
    capture.release()
    bars = {}
    if picture is not None and index:
        rows, columns = picture
        bars = {"bars": {"frame": [frame_shape[1], frame_shape[0]],
                         "kept": [columns.start, rows.start, columns.stop - columns.start, rows.stop - rows.start]}}
    return kept, {"seconds": round(index / fps, 2), "fps": fps, "total_motion": round(total_motion + counted, 4),
                  "most_frames": index // min_gap + 1, "due": due, **bars}
