"""Checks of a COLMAP model against the evidence it was built from: registered images nothing ties to the rest of
the model, and images whose poses contradict their own verified matches. A mapper can register either at a low
reprojection error while placing it wrongly, so these decide whether a model is kept, replaced or trimmed. And a check
of the matches themselves: a still background behind a turning object (a turntable in front of a room), which no
model of one rigid scene can hold."""
from __future__ import annotations

from collections import Counter
from pathlib import Path

import numpy as np
import pycolmap

# A pair counts as verified with at least this many geometric inliers (COLMAP's default).
MIN_VERIFIED_INLIERS = 15
# A registered image is tied to the model when it observes at least this many points that images already tied to it
# observe too (the loosest PnP support the relaxed mapping pass accepts). An image or group that is not tied has a pose
# nothing relates to the rest: its own few points fit it, so the reprojection error stays low while it can sit anywhere.
MIN_TIED_POINTS = 15
# A verified match lies within COLMAP's RANSAC error (4 px) of its epipolar line; a model contradicts it when its
# relative pose puts the match farther than that. Correct models contradict a few of an image's verified matches (some
# verified matches are wrong), wrong poses a large share of them (bench/README.md, "Poses"). Replacing a global model
# costs only a mapping run, so a
# lower share triggers it than the one that marks an image of a final model as misplaced (which leaves it out, and
# when too many images are, makes the model again or refuses it), which must not cry wolf.
EPIPOLAR_MAX_ERROR_PX = 4.0
GLOBAL_MAX_CONTRADICTED_SHARE = 0.1
MAX_CONTRADICTED_SHARE = 0.2
# A match that moved less than this share of the image's diagonal between its two photos sits at the same pixels. A
# pair is split when at least MIN_VERIFIED_INLIERS of its matches sit still and as many move, and its verified
# two-view geometry takes in all but STILL_SPLIT_SHARE of one group and at most that share of the other: what moved did not move as a rigid
# scene with what stood still (far content seen from cameras that only slid sideways sits still too, but agrees with
# the near content's geometry, and so does a pair taken twice from one spot). A capture has a still background when
# STILL_MIN_SHARE of all its matches sit still and some pairs are split: a turntable without masks has nearly all its
# matches still, a handheld or forward capture a few (bench/README.md, "Poses").
STILL_SHARE_OF_DIAGONAL = 0.004
STILL_MIN_SHARE = 0.25
STILL_SPLIT_SHARE = 0.25
STILL_MIN_SPLIT_PAIRS = 2
# At most about this many image pairs are read to count still matches (an even sample of them where there are more).
STILL_MAX_PAIRS = 3000
# Below STILL_MIN_SHARE, a refusal still names this share of still matches as a cause to look at.
STILL_HINT_SHARE = 0.1
# An imported pose contradicts its photo's matches where fewer than IMPORTED_MIN_AGREEING of the photo's matches with
# its nearby photos (those that pass the ratio test, IMPORTED_MIN_MATCHES of them at least) lie on the epipolar lines
# the poses give. Poses the photos fit: 23-89% of an image's matches agree (cup's, fox's, ball's and fern's); poses
# shuffled among the photos: 0-4%; a pose turned 3 degrees: 0-29%, most below 10% (bench/README.md, "Poses").
IMPORTED_MIN_AGREEING = 0.1
IMPORTED_MIN_MATCHES = 100


def detached_images(model: pycolmap.Reconstruction) -> list[str]:
    """Stems of the registered images not tied to the model's main block, grown from the image with the most points
    by adding every image that observes MIN_TIED_POINTS points the block observes."""
    registered = [im for im in model.images.values() if im.has_pose]
    if not registered:
        return []
    column = {im.image_id: n for n, im in enumerate(registered)}
    observer, point = [], []
    for n, point3d in enumerate(model.points3D.values()):
        for element in point3d.track.elements:
            if element.image_id in column:
                observer.append(column[element.image_id])
                point.append(n)
    observer, point = np.asarray(observer, dtype=np.int64), np.asarray(point, dtype=np.int64)
    tied = np.zeros(len(registered), dtype=bool)
    tied[np.argmax([im.num_points3D for im in registered])] = True
    while True:
        seen_by_block = np.bincount(point, weights=tied[observer], minlength=model.num_points3D()) > 0
        support = np.bincount(observer, weights=seen_by_block[point], minlength=len(registered))
        joining = ~tied & (support >= MIN_TIED_POINTS)
        if not joining.any():
            return sorted(Path(im.name).stem for im, ok in zip(registered, tied) if not ok)
        tied |= joining


def _skew(v: np.ndarray) -> np.ndarray:
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


def contradicted_images(db: Path, model: pycolmap.Reconstruction, above: float) -> dict[str, float]:
    """Registered images whose poses in the model contradict more than `above` of their verified matches, and the share."""
    posed = {im.name: im for im in model.images.values() if im.has_pose}
    with pycolmap.Database.open(db) as database:
        names = {image.image_id: image.name for image in database.read_all_images()}
        pair_ids, geometries = database.read_two_view_geometries()
        keypoints = {i: database.read_keypoints(i)[:, :2].astype(np.float64) for i in names if names[i] in posed}
    matches, contradicted = Counter(), Counter()
    for pair_id, geometry in zip(pair_ids, geometries):
        a, b = pycolmap.pair_id_to_image_pair(pair_id)
        inliers = geometry.inlier_matches
        if len(inliers) < MIN_VERIFIED_INLIERS or names[a] not in posed or names[b] not in posed:
            continue
        image_a, image_b = posed[names[a]], posed[names[b]]
        camera_a, camera_b = model.cameras[image_a.camera_id], model.cameras[image_b.camera_id]
        b_from_a = image_b.cam_from_world() * image_a.cam_from_world().inverse()
        baseline = np.linalg.norm(b_from_a.translation)
        if baseline == 0:  # two views from one centre have no epipolar geometry to contradict
            continue
        essential = _skew(b_from_a.translation / baseline) @ b_from_a.rotation.matrix()
        rays_a = np.c_[camera_a.cam_from_img(keypoints[a][inliers[:, 0]]), np.ones(len(inliers))]
        rays_b = np.c_[camera_b.cam_from_img(keypoints[b][inliers[:, 1]]), np.ones(len(inliers))]
        line_b, line_a = rays_a @ essential.T, rays_b @ essential
        # Sampson distance on the normalised image plane, in pixels of image a
        sampson = np.abs((rays_b * line_b).sum(1)) / np.sqrt(line_b[:, 0] ** 2 + line_b[:, 1] ** 2 + line_a[:, 0] ** 2 + line_a[:, 1] ** 2)
        wrong = int((sampson * camera_a.mean_focal_length() > EPIPOLAR_MAX_ERROR_PX).sum())
        for name in (names[a], names[b]):
            matches[name] += len(inliers)
            contradicted[name] += wrong
    shares = {Path(name).stem: contradicted[name] / matches[name] for name in matches}
    return {stem: round(share, 3) for stem, share in sorted(shares.items()) if share > above}


def unlinked_models(db: Path, best: pycolmap.Reconstruction, models: list[pycolmap.Reconstruction]) -> list[str]:
    """Stems of the images the other models pose that no matched pair (one geometric inlier is enough) ties to the
    images `best` poses, directly or through photos no model posed: where every pair was matched, what no attempt can
    join, as photos of separate scenes leave it. Empty where any of them is tied to `best`."""
    with pycolmap.Database.open(db) as database:
        names = {image.image_id: image.name for image in database.read_all_images()}
        pair_ids, inliers = database.read_two_view_geometry_num_inliers()
    component = {image_id: image_id for image_id in names}

    def root(image_id: int) -> int:
        while component[image_id] != image_id:
            component[image_id] = component[component[image_id]]
            image_id = component[image_id]
        return image_id
    for pair_id, count in zip(pair_ids, inliers):
        if count:
            a, b = pycolmap.pair_id_to_image_pair(pair_id)
            component[root(a)] = root(b)
    by_name = {name: image_id for image_id, name in names.items()}
    posed = {im.name for im in best.images.values() if im.has_pose}
    reached = {root(by_name[name]) for name in posed if name in by_name}
    elsewhere = {im.name for m in models if m is not best for im in m.images.values() if im.has_pose} - posed
    if any(name not in by_name or root(by_name[name]) in reached for name in elsewhere):
        return []
    return sorted(Path(name).stem for name in elsewhere)


def disagreeing_frames(agreement: np.ndarray, frames: int) -> dict[int, float]:
    """The frames (by index) whose matches with nearby photos mostly lie off the epipolar lines of their poses, each
    with the share that lies on them; `agreement` holds a row a pair: its frames, its matches, those that agree."""
    matches, agreeing = np.zeros(frames), np.zeros(frames)
    for i, j, found, kept in agreement:
        matches[[i, j]] += found
        agreeing[[i, j]] += kept
    share = agreeing / np.maximum(matches, 1)
    judged = (matches >= IMPORTED_MIN_MATCHES) & (share < IMPORTED_MIN_AGREEING)
    return {int(i): float(share[i]) for i in np.flatnonzero(judged)}


def drop_images(model: pycolmap.Reconstruction, stems: list[str]) -> None:
    for image in model.images.values():
        if image.has_pose and Path(image.name).stem in stems:
            model.deregister_frame(image.frame_id)


def still_matches(db: Path) -> dict:
    """How many of the matches between photos sit at the same pixels in both (`still`, of `matches`), and in how many
    pairs still matches and moving ones do not fit one rigid scene (`split_pairs`, of `pairs`: every matched pair, or
    an even sample of STILL_MAX_PAIRS); `still_background`: whether together they show a still background behind
    something that moved (see STILL_MIN_SHARE)."""
    total = still = split = pairs = 0
    with pycolmap.Database.open(db) as database:
        images = {image.image_id: image for image in database.read_all_images()}
        cameras = {camera.camera_id: camera for camera in database.read_all_cameras()}
        keypoints = {i: database.read_keypoints(i)[:, :2] for i in images}
        pair_ids, counts = database.read_num_matches()
        matched = [pair_id for pair_id, count in zip(pair_ids, counts) if count]
        # An even sample of the pairs where there are many: their matches are read one pair at a time.
        for pair_id in matched[::max(1, len(matched) // STILL_MAX_PAIRS)]:
            a, b = pycolmap.pair_id_to_image_pair(pair_id)
            pair = database.read_matches(a, b)
            camera = cameras[images[a].camera_id]
            moved = np.linalg.norm(keypoints[a][pair[:, 0]] - keypoints[b][pair[:, 1]], axis=1)
            sitting = moved < STILL_SHARE_OF_DIAGONAL * np.hypot(camera.width, camera.height)
            total, still, pairs = total + len(pair), still + int(sitting.sum()), pairs + 1
            if min(sitting.sum(), (~sitting).sum()) >= MIN_VERIFIED_INLIERS:
                inliers = database.read_two_view_geometry(a, b).inlier_matches.astype(np.int64)
                verified = np.isin(pair[:, 0].astype(np.int64) << 32 | pair[:, 1], inliers[:, 0] << 32 | inliers[:, 1])
                shares = sorted((verified[sitting].mean(), verified[~sitting].mean()))
                split += shares[0] <= STILL_SPLIT_SHARE and shares[1] >= 1 - STILL_SPLIT_SHARE
    share = still / total if total else 0.0
    return {"matches": total, "still": still, "share": round(share, 4), "pairs": pairs, "split_pairs": int(split),
            "still_background": bool(share >= STILL_MIN_SHARE and split >= STILL_MIN_SPLIT_PAIRS)}
