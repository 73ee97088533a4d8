"""COLMAP structure from motion through pycolmap: SIFT extraction (with EXIF focal priors where the photos are the size
the camera recorded), exhaustive or sequential matching, incremental or global mapping, and the checks that keep a
wrong or partial model from being used: a global model that contradicts its matches is mapped again incrementally,
sequential matching that leaves photos out is completed by exhaustive matching, images left out are retried with
looser registration thresholds, and a model that contradicts its own matches or splits in parts is made again in
safer configurations (`attempt_plan`) or refused with what the user can do. Where the photos carry masks of the
object, features come from inside them only, so a turntable's still background can neither hold a model together
nor tear it apart; without masks, matches that sit at the same pixels across photos while others move (a still
background behind a turning object) stop SfM with that reason before any model is made of them."""
from __future__ import annotations

import shutil
import statistics
import time
from collections import Counter
from contextlib import contextmanager
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Iterator

import cv2
import numpy as np
import pycolmap

from stages.capture.panorama import is_two_to_one
from stages.common.text import short_list
from stages.sfm import gps
from stages.sfm.exif import one_camera, resized_since_capture, set_focal_priors
from stages.sfm.lens import PINHOLE_LENS_MODELS, lens_words, may_be_fisheye, probe_images, wide_lens
from stages.sfm.mapping import colmap_threads, incremental_mapping, largest_model, map_images
from stages.sfm.model_checks import (MAX_CONTRADICTED_SHARE, MIN_VERIFIED_INLIERS, STILL_HINT_SHARE,
                                       contradicted_images, detached_images, drop_images, still_matches,
                                       unlinked_models)
from stages.sfm.options import SfmOptions
from plenoxels.core.errors import UserError

# COLMAP's own detection threshold; lowered by this factor when images yield too few features.
SIFT_PEAK_THRESHOLD = 0.02 / 3
LOW_FEATURE_PEAK_DIVISOR = 3.0
# Loop closure's visual words: descriptors sampled per image, the share of them that trains the vocabulary, its size.
LOOP_WORD_SAMPLES = 2000
LOOP_TRAINING_PER_IMAGE = 300
LOOP_VOCABULARY = 256
# Repairs match every pair up to this many images (COLMAP's exhaustive matching grows with the square).
REPAIR_EXHAUSTIVE_MAX_IMAGES = 400
# A repair extracts features on images downscaled to this side (the `fast` preset's photos), where larger ones do not
# hold together: COLMAP puts the keypoints back in full-size pixels, so the cameras come out for the photos as they
# are. A phone video's frames that pose at 640 px have failed the check at 960, 8 to 9 of 52 contradicting their
# matches after every other repair.
REPAIR_FEATURE_SIDE = 640
# A 360 capture's views are matched in sequence with those of this many frames on either side.
PANORAMA_OVERLAP_FRAMES = 3
# How a model split in parts is named among its problems (a split no retry can join is dropped from them).
SPLIT_WORDS = "the images split into"


@contextmanager
def colmap_logging(verbose: bool) -> Iterator[None]:
    """COLMAP logs every step through glog; by default only its errors get through."""
    previous = (pycolmap.logging.minloglevel, pycolmap.logging.stderrthreshold)
    if not verbose:
        pycolmap.logging.minloglevel = 2
        pycolmap.logging.stderrthreshold = 2
    try:
        yield
    finally:
        pycolmap.logging.minloglevel, pycolmap.logging.stderrthreshold = previous


def pycolmap_device(use_gpu: bool) -> pycolmap.Device:
    return pycolmap.Device.cuda if use_gpu and pycolmap.has_cuda else pycolmap.Device.cpu


def feature_masks(records: list[dict], ingest_dir: Path, folder: Path) -> Path | None:
    """The ingested masks as COLMAP reads them (`<image name>.png` in `folder`: black where no feature may be
    extracted, the pixels under half the object's weight), or None when no image has a mask."""
    masked = [r for r in records if r.get("mask")]
    if not masked:
        return None
    shutil.rmtree(folder, ignore_errors=True)
    folder.mkdir(parents=True)
    for record in masked:
        mask = cv2.imread(str(ingest_dir / record["mask"]), cv2.IMREAD_GRAYSCALE)
        cv2.imwrite(str(folder / f"{record['name']}.png.png"), np.where(mask >= 128, 255, 0).astype(np.uint8))
    return folder


def extract_features(db: Path, image_dir: Path, names: list[str], s: SfmOptions, single_camera: bool,
                     peak_threshold: float, masks: Path | None = None) -> None:
    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = s.camera_model
    if masks is not None:
        reader.mask_path = str(masks)
    options = pycolmap.FeatureExtractionOptions()
    options.sift.max_num_features = s.max_features
    options.sift.peak_threshold = peak_threshold
    options.max_image_size = s.feature_max_side or -1
    options.use_gpu = s.use_gpu and pycolmap.has_cuda
    options.num_threads = colmap_threads(s)
    db.unlink(missing_ok=True)
    pycolmap.extract_features(db, image_dir, image_names=names,
                              camera_mode=pycolmap.CameraMode.SINGLE if single_camera else pycolmap.CameraMode.PER_IMAGE,
                              reader_options=reader, extraction_options=options, device=pycolmap_device(s.use_gpu))


def median_features(db: Path) -> float:
    with pycolmap.Database.open(db) as database:
        return statistics.median(database.num_keypoints_for_image(image.image_id) for image in database.read_all_images())


def match_features(db: Path, mode: str, s: SfmOptions) -> None:
    options = pycolmap.FeatureMatchingOptions()
    options.use_gpu = s.use_gpu and pycolmap.has_cuda
    options.num_threads = colmap_threads(s)
    verification = pycolmap.TwoViewGeometryOptions()
    verification.ransac.random_seed = s.seed
    device = pycolmap_device(s.use_gpu)
    if mode == "sequential":
        pairing = pycolmap.SequentialPairingOptions()
        pairing.overlap = s.sequential_overlap
        pycolmap.match_sequential(db, matching_options=options, pairing_options=pairing,
                                  verification_options=verification, device=device)
    else:
        pycolmap.match_exhaustive(db, matching_options=options, verification_options=verification, device=device)


def loop_pairs(db: Path, overlap: int, neighbours: int, seed: int) -> list[tuple[str, str]]:
    """Image pairs that close the loops of a sequence (images in name order, as sequential matching takes them): the
    first `overlap` images with the last `overlap`, and each image with its `neighbours` most alike images farther
    than `overlap` along the sequence. Alike means close bags of visual words: the SIFT descriptors already in the
    database quantised by a small vocabulary learnt from them, weighted by TF-IDF, compared by cosine."""
    with pycolmap.Database.open(db) as database:
        images = sorted(database.read_all_images(), key=lambda im: im.name)
        descriptors = [np.asarray(database.read_descriptors(im.image_id).data, dtype=np.float32) for im in images]
    n = len(images)
    pairs = {(i, j) for i in range(min(overlap, n)) for j in range(max(n - overlap, 0), n) if j - i > overlap}
    rng = np.random.default_rng(seed)
    sampled = [d[rng.choice(len(d), min(len(d), LOOP_WORD_SAMPLES), replace=False)] for d in descriptors if len(d)]
    if neighbours > 0 and sampled:
        training = np.concatenate([d[:LOOP_TRAINING_PER_IMAGE] for d in sampled])
        words = min(LOOP_VOCABULARY, max(2, len(training) // 20))
        cv2.setRNGSeed(seed)
        criteria = (cv2.TERM_CRITERIA_MAX_ITER + cv2.TERM_CRITERIA_EPS, 10, 1.0)
        _, _, centres = cv2.kmeans(training, words, None, criteria, 1, cv2.KMEANS_PP_CENTERS)
        histograms = np.zeros((n, words))
        for i, d in enumerate(descriptors):
            d = d[rng.choice(len(d), min(len(d), LOOP_WORD_SAMPLES), replace=False)] if len(d) else d
            if len(d):
                nearest = ((d ** 2).sum(1)[:, None] - 2 * d @ centres.T + (centres ** 2).sum(1)[None]).argmin(1)
                histograms[i] = np.bincount(nearest, minlength=words)
        idf = np.log(n / np.maximum((histograms > 0).sum(0), 1))
        weighted = histograms / np.maximum(histograms.sum(1, keepdims=True), 1) * idf
        weighted /= np.maximum(np.linalg.norm(weighted, axis=1, keepdims=True), 1e-12)
        similarity = weighted @ weighted.T
        index = np.arange(n)
        similarity[np.abs(index[:, None] - index[None]) <= overlap] = -np.inf
        for i in range(n):
            for j in np.argsort(-similarity[i])[:neighbours]:
                if np.isfinite(similarity[i, j]):
                    pairs.add((min(i, int(j)), max(i, int(j))))
    return [(images[i].name, images[j].name) for i, j in sorted(pairs)]


def match_loop_pairs(db: Path, s: SfmOptions, scratch: Path) -> int:
    """Matches (and verifies) the loop-closing pairs of a sequence; returns how many pairs were asked for."""
    pairs = loop_pairs(db, s.sequential_overlap, s.loop_neighbours, s.seed)
    if not pairs:
        return 0
    listing = scratch / "loop_pairs.txt"
    listing.write_text("".join(f"{a} {b}\n" for a, b in pairs))
    options = pycolmap.FeatureMatchingOptions()
    options.use_gpu = s.use_gpu and pycolmap.has_cuda
    options.num_threads = colmap_threads(s)
    pairing = pycolmap.ImportedPairingOptions()
    pairing.match_list_path = str(listing)
    verification = pycolmap.TwoViewGeometryOptions()
    verification.ransac.random_seed = s.seed
    pycolmap.match_image_pairs(db, matching_options=options, pairing_options=pairing,
                               verification_options=verification, device=pycolmap_device(s.use_gpu))
    return len(pairs)


def matching_summary(db: Path) -> dict:
    """Pairs matched and verified, and the images with fewer than two verified partners."""
    with pycolmap.Database.open(db) as database:
        names = {image.image_id: image.name for image in database.read_all_images()}
        pair_ids, inliers = database.read_two_view_geometry_num_inliers()
        matched = database.num_matched_image_pairs()
    partners: Counter = Counter()
    verified = 0
    for pair_id, count in zip(pair_ids, inliers):
        if count >= MIN_VERIFIED_INLIERS:
            verified += 1
            a, b = pycolmap.pair_id_to_image_pair(pair_id)
            partners[a] += 1
            partners[b] += 1
    poorly = sorted(Path(names[i]).stem for i in names if partners[i] < 2)
    return {"pairs_matched": matched, "pairs_verified": verified, "poorly_matched": poorly,
            "inlier_matches": int(sum(c for c in inliers if c >= MIN_VERIFIED_INLIERS))}


def _match_and_summarise(db: Path, mode: str, s: SfmOptions, n_images: int, report, seconds: dict) -> dict:
    started = time.perf_counter()
    report.info(f"matching features ({mode})")
    match_features(db, "exhaustive" if mode.startswith("exhaustive") else mode, s)
    if mode == "sequential" and s.loop_neighbours > 0:
        asked = match_loop_pairs(db, s, db.parent)
        report.info(f"matched {asked} loop-closing pairs (first with last images, and alike images)")
    seconds["match"] += time.perf_counter() - started
    matching = matching_summary(db)
    report.info(f"matching: {matching['pairs_verified']} of {matching['pairs_matched']} image pairs verified, "
                f"{matching['inlier_matches']} inlier matches")
    poorly = matching.pop("poorly_matched")
    if poorly:
        report.warn(f"{len(poorly)} image(s) verified with fewer than 2 others, so they may not register: {short_list(poorly)}")
    if matching["pairs_verified"] < n_images - 1:
        report.warn(f"only {matching['pairs_verified']} image pairs verified for {n_images} images; the photos "
                    "may overlap too little (take more, closer together)")
    return matching


@dataclass
class Attempt:
    """One configuration SfM is run with: the options, whether the cameras start from the EXIF focal length, whether
    they are known (a 360 frame's views: their focal length given, kept by bundle adjustment), and whether a few
    images are mapped first to see if the lens is a fisheye's (`lens.probe_images`)."""
    label: str
    options: SfmOptions
    focal_prior: bool
    peak_threshold: float = SIFT_PEAK_THRESHOLD
    known_cameras: bool = False
    probe_lens: bool = False


def attempt_plan(s: SfmOptions, n_images: int, from_video: bool, longest_side: int = 0) -> list[Attempt]:
    """The configuration as set, then each safer one in turn, every step keeping the ones before it: exhaustive
    matching (which sees every pair, so a loop closes and a bad sequence link is outvoted), no EXIF focal prior (a
    cropped or mislabelled photo's focal starts verification from the wrong essential matrices), features from images
    of REPAIR_FEATURE_SIDE where the photos' `longest_side` is larger (that attempt alone; the next go on at the
    size before), twice the features at a lower detection threshold, and features from the full-size ingested
    images."""
    plan = [Attempt("as set", s, s.exif_focal)]
    if not s.repair:
        return plan
    current, prior = s, s.exif_focal
    matching = s.matching if s.matching != "auto" else (
        "sequential" if from_video or n_images > s.exhaustive_max_images else "exhaustive")
    if matching != "exhaustive" and n_images <= REPAIR_EXHAUSTIVE_MAX_IMAGES:
        current = replace(current, matching="exhaustive")
        plan.append(Attempt("exhaustive matching", current, prior))
    if prior:
        prior = False
        plan.append(Attempt("no EXIF focal prior", current, prior))
    smaller = smaller_features(Attempt("", current, prior), longest_side)
    if smaller is not None:
        plan.append(smaller)
    current = replace(current, max_features=2 * current.max_features, min_features=2 * current.min_features)
    peak = SIFT_PEAK_THRESHOLD / LOW_FEATURE_PEAK_DIVISOR
    plan.append(Attempt("twice the features", current, prior, peak))
    if current.feature_max_side:
        current = replace(current, feature_max_side=0)
        plan.append(Attempt("full-size images", current, prior, peak))
    return plan


def as_fisheye(attempt: Attempt) -> Attempt:
    """`attempt` with an OPENCV_FISHEYE camera, and no lens probe."""
    return replace(attempt, options=replace(attempt.options, camera_model="OPENCV_FISHEYE"), probe_lens=False)


def smaller_features(attempt: Attempt, longest_side: int) -> Attempt | None:
    """`attempt` with features from images of REPAIR_FEATURE_SIDE, where the photos are larger and its features are
    not already that small."""
    if longest_side <= REPAIR_FEATURE_SIDE or 0 < attempt.options.feature_max_side <= REPAIR_FEATURE_SIDE:
        return None
    options = replace(attempt.options, feature_max_side=REPAIR_FEATURE_SIDE)
    return replace(attempt, label=f"features at {REPAIR_FEATURE_SIDE} px", options=options)


def contradicting(contradicted: dict[str, float], n_images: int) -> str:
    """The words for a model's images that contradict their matches: a refused model's problem, or what it left out."""
    return (f"{len(contradicted)}/{n_images} images have poses that contradict over {MAX_CONTRADICTED_SHARE:.0%} of "
            f"their verified matches ({short_list(sorted(contradicted))})")


def model_problems(db: Path, best: pycolmap.Reconstruction | None, models: list[pycolmap.Reconstruction],
                   n_images: int, s: SfmOptions) -> tuple[list[str], dict[str, float]]:
    """Why a model cannot be trusted (none: it holds together), and its images that contradict their matches."""
    if best is None:
        return ["no model formed"], {}
    contradicted = contradicted_images(db, best, MAX_CONTRADICTED_SHARE)
    problems = []
    if len(contradicted) > s.max_contradicted_images * n_images:
        problems.append(contradicting(contradicted, n_images))
    posed = {im.name for im in best.images.values() if im.has_pose}
    elsewhere = {im.name for m in models if m is not best for im in m.images.values() if im.has_pose} - posed
    if len(elsewhere) >= 2:
        problems.append(f"{SPLIT_WORDS} {len(models)} separate models; {len(elsewhere)} are outside the "
                        f"largest ({short_list(sorted(Path(n).stem for n in elsewhere))})")
    return problems, contradicted


def reconstruct(records: list[dict], image_dir: Path, photos: Path, from_video: bool, scratch: Path,
                s: SfmOptions, report, min_share: float = 1.0) -> tuple[pycolmap.Reconstruction, dict]:
    """The largest model COLMAP makes of the ingested images (`records`, PNGs in `image_dir`, original photos in
    `photos` for their EXIF) that holds together: each configuration of `attempt_plan` in turn until one gives a model
    that neither contradicts its own matches nor splits in parts. Images left detached or contradicting their matches
    are dropped from it, once a model from smaller features (`smaller_features`) has been tried for them; with no
    such model the stage stops with what the user can do. Photos that share not one match with the model's, once
    every pair was matched, show something else: left out where the model poses `min_share` of the photos, else the
    stage stops, naming them. Returns the model and what happened on the way (attempts, counts, fallbacks, timings).
    `scratch` holds the databases and models."""
    longest_side = max(max(r["width"], r["height"]) for r in records)
    plan = attempt_plan(s, len(records), from_video or any("panorama" in r for r in records), longest_side)
    if all("focal" in r for r in records):  # a 360 capture's views: pinholes of the focal length they were cut at
        panorama = [r for r in records if "panorama" in r]
        frames = len({r["panorama"]["frame"] for r in panorama})
        overlap = max(s.sequential_overlap, PANORAMA_OVERLAP_FRAMES * round(len(panorama) / max(frames, 1)))
        plan = [replace(a, known_cameras=True, options=replace(a.options, sequential_overlap=overlap,
                                                               camera_model="PINHOLE"))
                for a in plan if a.label != "no EXIF focal prior"]  # nor is an EXIF focal length used for them
    elif s.repair and s.camera_model in PINHOLE_LENS_MODELS:
        plan[0] = replace(plan[0], probe_lens=True)
    masks = feature_masks(records, image_dir.parent, scratch / "feature_masks")
    if masks is not None:
        report.info(f"features only inside the masks of {sum(bool(r.get('mask')) for r in records)} images")
    resized = resized_since_capture(records, photos) if s.exif_focal else []
    if resized:
        report.info(f"{len(resized)} photo(s) are not the size their EXIF says the camera recorded (cropped or resized), "
                    "so their EXIF focal length is not used")
    tried = []
    for number, attempt in enumerate(plan):
        best, info, models = sfm_attempt(records, image_dir, photos, from_video, scratch / f"attempt_{number}",
                                         attempt, report, masks)
        db = info.pop("db")
        if "lens_probe" in info:  # made as a fisheye: so are the attempts after it
            attempt = as_fisheye(attempt)
            plan[number + 1:] = [as_fisheye(a) for a in plan[number + 1:]]
        problems, contradicted = model_problems(db, best, models, len(records), attempt.options)
        separate = unlinked_models(db, best, models) if best and info["matching"].startswith("exhaustive") else []
        if len(separate) >= 2 and best.num_reg_images() < min_share * len(records):
            raise UserError(f"these photos show separate scenes (or parts of one that no photo overlaps): after "
                            f"every pair was matched, none of the {len(separate)} photos the largest pose model leaves "
                            f"out ({short_list(separate)}) shares one match with its {best.num_reg_images()}; give "
                            "each scene its own folder, or add photos that overlap both")
        if len(separate) >= 2:  # no retry joins what shares no match: the model stands without them
            problems = [problem for problem in problems if not problem.startswith(SPLIT_WORDS)]
            info["other_scene"] = separate
            report.warn(f"{len(separate)} photos share not one match with the {best.num_reg_images()} of the pose "
                        f"model, after every pair was matched: they show something else, and are left out "
                        f"({short_list(separate)})")
        tried.append({"attempt": attempt.label, "registered": best.num_reg_images() if best else 0,
                      "contradicted": len(contradicted), "models": len(models), "problems": problems})
        if not problems:
            break
        following = f"; trying {plan[number + 1].label}" if number + 1 < len(plan) else ""
        report.warn(f"SfM ({attempt.label}): {'; '.join(problems)}{following}")
    else:
        still = info["still_matches"]
        hint = (f"; {still['share']:.0%} of the matched features sit at the same pixels in both photos of a pair, as a "
                "still background behind a turning object leaves them: if the object turned, give a mask of it for "
                "each photo (a masks/ folder beside the photos)" if still["share"] >= STILL_HINT_SHARE else "")
        if all(is_two_to_one(r["width"], r["height"]) and "panorama" not in r for r in records):
            hint += ("; the photos are 2:1, as a 360 camera's equirectangular frames are: if they are, set "
                     "ingest.equirect=yes")
        if all(t["problems"] == ["no model formed"] for t in tried):
            raise UserError(f"SfM formed no model from {len(records)} images ({info['pairs_verified']} verified pairs); "
                            f"the photos need more overlap and texture, or give poses with poses.source/poses.path{hint}")
        raise UserError(f"no pose model of these photos holds together after {len(tried)} attempt(s) "
                        f"({', '.join(t['attempt'] for t in tried)}): {tried[-1]['problems'][0]}; take sharper, "
                        "more overlapping photos (or drop those named), or try poses.matching, poses.camera_model or "
                        f"poses.exif_focal=false{hint}")
    why = tried[0]["problems"][0] if number else None
    # A model that holds together but leaves photos out as contradicting their matches, its features from photos
    # larger than REPAIR_FEATURE_SIDE: the same configuration at that side may pose them (a phone video's frames
    # misplaced at 960 px, contradicting 22-78% of their matches, hold together at 640); kept where it poses more.
    def instead(other: Attempt):
        """`other` run beside the model in hand: its model, information and contradicted images, and how many images
        it poses that hold (0 where the model has problems)."""
        try:
            again, again_info, again_models = sfm_attempt(records, image_dir, photos, from_video,
                                                          scratch / f"attempt_{len(tried)}", other, report, masks)
        except UserError:  # this attempt alone refusing what the model in hand got past: keep that model
            again, again_info, again_models = None, {"db": None}, []
        problems, again_contradicted = model_problems(again_info.pop("db"), again, again_models, len(records),
                                                      other.options)
        tried.append({"attempt": other.label, "registered": again.num_reg_images() if again else 0,
                      "contradicted": len(again_contradicted), "models": len(again_models), "problems": problems})
        posed_again = again.num_reg_images() - len(again_contradicted) if again is not None and not problems else 0
        return again, again_info, again_contradicted, posed_again

    smaller = smaller_features(attempt, longest_side) if contradicted and s.repair else None
    if smaller is not None:
        left_out = contradicting(contradicted, len(records))
        report.warn(f"SfM ({attempt.label}): {left_out}; trying {smaller.label}")
        again, again_info, again_contradicted, posed_again = instead(smaller)
        if posed_again > best.num_reg_images() - len(contradicted):
            why = why or left_out
            best, info, contradicted, attempt, number = again, again_info, again_contradicted, smaller, len(tried) - 1
    # A lens wider than the model fitted describes (an action camera's fisheye): made again as a fisheye, kept where
    # it poses as many images and they reproject closer (a 150-degree fisheye: 1.2 px and 1 degree off as
    # SIMPLE_RADIAL, 0.3 px and under 0.01 degree as OPENCV_FISHEYE).
    stretch = wide_lens(best) if s.repair else None
    if stretch is not None:
        fisheye = replace(as_fisheye(attempt), label="a fisheye lens model")
        bent = lens_words(stretch, attempt.options.camera_model)
        report.warn(f"SfM ({attempt.label}): {bent}; trying {fisheye.label}")
        again, again_info, again_contradicted, posed_again = instead(fisheye)
        if posed_again and posed_again >= best.num_reg_images() - len(contradicted) and (
                again.compute_mean_reprojection_error() < best.compute_mean_reprojection_error()):
            why = why or bent
            best, info, contradicted, attempt, number = again, again_info, again_contradicted, fisheye, len(tried) - 1
    info["attempts"], info["attempt"] = tried, attempt.label
    if number:
        info["attempt_why"] = why
    info["exif_resized"] = resized
    info["masked_images"] = sum(bool(r.get("mask")) for r in records) if masks is not None else 0
    if contradicted:
        drop_images(best, sorted(contradicted))
        info["contradicted"] = contradicted
        report.warn(f"the poses of {len(contradicted)} image(s) contradict over {MAX_CONTRADICTED_SHARE:.0%} of their "
                    f"verified matches, so they are left out: {short_list(sorted(contradicted))}")
    return best, info


def refuse_still(still: dict, masked: bool) -> None:
    """Stops SfM where its matches show a still background behind something that moved (model_checks.still_matches):
    photos of an object turning in front of a room it does not turn with, which no rigid model holds and no fit shows."""
    if not still["still_background"]:
        return
    where = "even inside the masks given: the masks take in the background" if masked else "as on a turntable"
    raise UserError(f"the photos show a still background behind a turning object: {still['share']:.0%} of "
                    f"{still['matches']} matched features sit at the same pixels in both photos of a pair, and in "
                    f"{still['split_pairs']} pairs they and the others, which move, fit no one rigid scene ({where}); "
                    "give a mask of the object for each photo (a masks/ folder beside the photos, white on the "
                    "object, each named like its photo)")


def sfm_attempt(records: list[dict], image_dir: Path, photos: Path, from_video: bool, scratch: Path,
                attempt: Attempt, report, masks: Path | None = None
                ) -> tuple[pycolmap.Reconstruction | None, dict, list[pycolmap.Reconstruction]]:
    """One SfM run in one configuration, features only inside `masks` (COLMAP's mask folder) when given: the largest
    model with detached images dropped, what happened on the way (with the database's path under "db") and every
    model the mapper made. Matches that show a still background behind a moving object stop it (`refuse_still`)."""
    s = attempt.options
    scratch.mkdir(parents=True, exist_ok=True)
    db = scratch / "database.db"
    names = [f"{r['name']}.png" for r in records]
    seconds: dict[str, float] = {}
    info: dict = {"db": db}

    single = {"yes": True, "no": False}.get(s.shared_camera) if s.shared_camera != "auto" else one_camera(records, photos)
    info["shared_camera"] = single
    started = time.perf_counter()
    device = "GPU" if pycolmap_device(s.use_gpu) == pycolmap.Device.cuda else "CPU"
    report.info(f"extracting SIFT features from {len(names)} images ({device}, {'one shared camera' if single else 'one camera per image'}, {s.camera_model})")
    peak = attempt.peak_threshold
    extract_features(db, image_dir, names, s, single, peak, masks)
    median = median_features(db)
    if median < s.min_features:
        report.info(f"only {median:.0f} features per image (median); extracting again with a lower detection threshold")
        extract_features(db, image_dir, names, s, single, peak / LOW_FEATURE_PEAK_DIVISOR, masks)
        median = median_features(db)
    info["median_features"] = median
    info["focal_prior"] = set_focal_priors(db, records, photos, s.sensor_width_mm, attempt.focal_prior)
    if info["focal_prior"]:
        prior = info["focal_prior"]
        report.info(f"initial focal length {prior['focal_px']:.1f} px from {prior['from']} ({prior['images']} photos)")
    located = gps.photo_positions(records, photos) if s.gps_priors else {}
    survey = gps.survey_metres(located, len(records))
    stated = {name: error for name, error in gps.position_errors(records, photos).items() if name in (survey or {})}
    priors = survey is not None and gps.write_priors(db, survey, stated) >= 3
    if priors:  # metres of the first photo located: the frame the model comes out in
        info["gps_priors"] = {"photos": len(survey), "origin": list(next(iter(located.values())))}
        if stated:  # each at the error its source gives (an RTK fix, a log's rounding), not the one taken for all
            info["gps_priors"]["stated"] = [len(stated), round(float(np.median([e[0] for e in stated.values()])), 3)]
        report.info(f"holding the cameras near the GPS of {len(survey)} photos")
    seconds["extract"] = time.perf_counter() - started
    mode = s.matching
    if mode == "auto":
        mode = "sequential" if from_video or len(names) > s.exhaustive_max_images else "exhaustive"
    seconds["match"], seconds["map"] = 0.0, 0.0
    while True:
        matching = _match_and_summarise(db, mode, s, len(names), report, seconds)
        info["still_matches"] = still_matches(db)
        refuse_still(info["still_matches"], masks is not None)
        started = time.perf_counter()
        probed = probe_images(db) if attempt.probe_lens and may_be_fisheye(
            info["focal_prior"], records[0]["width"], records[0]["height"]) else []
        attempt = replace(attempt, probe_lens=False)
        if len(probed) >= 3:  # no names would map every image
            probe = largest_model(incremental_mapping(db, image_dir, scratch / "lens_probe", s, image_names=probed))
            stretch = wide_lens(probe)
            seconds["lens_probe"] = time.perf_counter() - started
            if stretch is not None:
                report.warn(f"SfM: {lens_words(stretch, s.camera_model)} in {probe.num_reg_images()} images mapped "
                            "first; making the model as OPENCV_FISHEYE")
                best, again, models = sfm_attempt(records, image_dir, photos, from_video, scratch / "fisheye",
                                                  as_fisheye(attempt), report, masks)
                again["lens_probe"] = {"stretch": stretch, "seconds": round(sum(seconds.values()), 2)}
                return best, again, models
            started = time.perf_counter()
        models, best, fallback = map_images(db, image_dir, scratch, s, report, attempt.known_cameras, priors)
        seconds["map"] += time.perf_counter() - started
        complete = best is not None and best.num_reg_images() == len(names) and not detached_images(best)
        # Photos that are not an ordered sequence lose pairs under sequential matching: when auto chose it for a
        # photo set and it leaves images out, match the remaining pairs too (matched pairs are not redone) and map again.
        if complete or mode != "sequential" or s.matching != "auto" or from_video:
            break
        report.info(f"{best.num_reg_images() if best else 0}/{len(names)} registered after sequential matching; "
                    "matching all remaining pairs")
        mode = "exhaustive after sequential"
    info["mapper"] = "incremental" if fallback else s.mapper
    if fallback:
        info["mapper_fallback"] = fallback
    info.update(matching, matching=mode, models=len(models))
    if (s.mapper == "incremental" or fallback) and not complete:
        started = time.perf_counter()
        before = best.num_reg_images() - len(detached_images(best)) if best else 0
        report.info(f"{before}/{len(names)} registered; mapping again with looser registration thresholds")
        relaxed = largest_model(incremental_mapping(db, image_dir, scratch / "models_relaxed", s, relaxed=True,
                                                    fixed_cameras=attempt.known_cameras, priors=priors))
        if relaxed is not None and relaxed.num_reg_images() - len(detached_images(relaxed)) > before:
            strict = {im.name for im in best.images.values() if im.has_pose} if best else set()
            info["relaxed_only"] = sorted(Path(im.name).stem for im in relaxed.images.values()
                                          if im.has_pose and im.name not in strict)
            best = relaxed
            report.warn(f"{len(info['relaxed_only'])} image(s) registered only with looser thresholds, so their poses "
                        f"are less certain: {short_list(info['relaxed_only'])}")
        seconds["map"] += time.perf_counter() - started
    info["seconds"] = seconds
    if len(models) > 1:
        sizes = sorted((m.num_reg_images() for m in models), reverse=True)
        report.warn(f"COLMAP made {len(models)} separate models ({', '.join(map(str, sizes))} images); using the largest")
    if best is None:
        return None, info, models
    unplaced = detached_images(best)
    if unplaced:
        drop_images(best, unplaced)
        info["detached"] = unplaced
        report.warn(f"{len(unplaced)} registered image(s) share too few points with the rest of the model to place "
                    f"them, so they are left out: {short_list(unplaced)}")
    return best, info, models
