"""Normalize: one scene frame (z up, foreground in the unit cube), the scene type, near/far per image,
and the train/held-out split, decided by stages/framing/scene_frame.py (which also says what each scene type means).

Reads poses/transforms.json and poses/points.npz; writes normalize/scene.json (see README.md).
"""
from __future__ import annotations

from stages.common.json_files import read_json, write_json
from stages.framing.scene_frame import normalize_scene
from stages.framing.sightings import read_points
from plenoxels.core.errors import UserError
from stages.common.layout import POINTS_NPZ, SCENE_JSON, TRANSFORMS_JSON


def summary_line(scene: dict) -> str:
    m = scene["measured"]
    if scene["type"] == "forward":
        why = f"viewing directions within {m['view_cone_deg']:.0f} deg"
    elif m.get("masked"):
        why = f"cameras inward, every photo masked ({m['empty_pixel_fraction']:.0%} of pixels outside the masks)"
    elif "beyond_fraction" in m:
        why = f"cameras inward, {m['beyond_fraction']:.0%} of points beyond the foreground"
        if "empty_pixel_fraction" in m:
            why += f", {m['empty_pixel_fraction']:.0%} of pixels empty backdrop"
    elif "empty_pixel_fraction" in m:
        why = f"cameras inward, no points, {m['empty_pixel_fraction']:.0%} of pixels empty backdrop"
    else:
        why = "cameras inward, no points"
    if m.get("own_backdrops"):
        why += f"; each photo on a flat backdrop of its own colour ({m['own_backdrops']:.0%} of them)"
    elif any("backdrop" in f for f in scene["frames"]):
        why += "; each photo's own colour outside its mask trained as empty"
    if m.get("foreground_from", "").startswith("visual hull"):
        silhouettes = "masks" if m["visual_hull"]["source"] == "masks" else "silhouettes on a flat backdrop"
        why += f"; box from the visual hull of {m['visual_hull']['photos']} photos' {silhouettes}"
    elif m.get("visual_hull") and m.get("foreground_from", "").endswith(" show"):
        silhouettes = "masks" if m["visual_hull"]["source"] == "masks" else "silhouettes on a flat backdrop"
        why += (f"; box from the points, grown to hold what {m['visual_hull']['photos']} photos' {silhouettes} show "
                "(their hull runs on out of the photos' frames)")
    if m.get("borderline") and not scene["overridden"]:
        why += f"; borderline: views spread {m['view_cone_deg']:.0f} deg, near the forward limit"
    if scene["overridden"]:
        why += f"; set by normalize.scene_type, detected {scene['detected']}"
    test = sum(f["split"] == "test" for f in scene["frames"])
    train = sum(f["split"] == "train" for f in scene["frames"])
    n = len(scene["frames"])
    colourless = sum(f["split"] == "unused" and bool(f.get("colourless")) for f in scene["frames"])
    skipped = n - train - test - colourless
    reasons = {(True, False): "normalize.train_every", (False, True): "without colour",
               (True, True): f"{skipped} by normalize.train_every, {colourless} without colour"}
    unused = f" / {n - train - test} unused ({reasons[skipped > 0, colourless > 0]})" if n - train - test else ""
    return f"{scene['type']} scene ({why}); {n} frames, {train} train / {test} held out{unused}"


def run(ctx) -> dict:
    poses_dir = ctx.upstream["poses"]
    transforms_path = poses_dir / TRANSFORMS_JSON
    if not transforms_path.is_file():
        raise UserError(f"{transforms_path} is missing; run the poses stage first")
    scene = normalize_scene(read_json(transforms_path), read_points(poses_dir / POINTS_NPZ),
                            ctx.settings, poses_dir)
    write_json(ctx.work / SCENE_JSON, scene)
    for reason in scene["reasons"]:
        ctx.report.info(f"normalize: {reason}")
    test = sum(f["split"] == "test" for f in scene["frames"])
    return {"line": summary_line(scene), "type": scene["type"], "frames": len(scene["frames"]),
            "held_out": test, "scale": scene["scale"]}
