"""Evaluate: the fitted model on the held-out views, and a novel-view video.

Writes evaluate/metrics.json (PSNR, SSIM and LPIPS per held-out view and their means), evaluate/renders/,
evaluate/gt/ and evaluate/depth/ (PNG per held-out view; depth colour-mapped between its 2nd and 98th
percentile over the pixels the model covers, black where it covers nothing), evaluate/video.mp4 (the
path that suits the capture: an orbit where the cameras surround the foreground, an arc through them
where they do not, a spiral for forward scenes; stages/scoring/camera_paths.py) and evaluate/contact_sheet.png
(ground truth | render | error, one row per held-out view, captioned with its scores).

Ground truth is the held-out photo resized to the evaluation scale, its mask (if any) composited onto
the fit's background colour exactly as the fit saw its training photos. Views with a mask are scored inside it too
(`psnr_masked`, `ssim_masked`: over the mask's pixels only, as the DTU protocol scores object captures), since the
whole image's score counts a backdrop any empty render matches. Where the fit measured each photo's colour
(`fit.photo_colour`: a phone's exposure and white balance) and the gains follow the capture's order, a held-out view is
rendered in the colour its neighbours in that order were taken in (plenoxels/core/photo_colour.py, PhotoGains), and
in their light across the frame where that follows the order too (`fit.photo_colour_cells`), from none of its own
pixels; the video is in the photos' common colour. SSIM is scikit-image's
structural_similarity (Gaussian-weighted, as in Wang et al. 2004) on RGB in [0, 1]; LPIPS is v0.1 with
AlexNet (stages/scoring/lpips.py), left out with a warning when its weights are not installed.
"""
from __future__ import annotations

import time

import imageio.v2 as imageio
import numpy as np
import torch

from stages.scoring.camera_paths import default_path, median_intrinsics
from stages.common.frames import read_frame
from stages.common.media import write_png
from stages.common.json_files import read_json, write_json
from stages.scoring.lpips import weights_available
from stages.scoring.metrics import image_scores, masked_scores, mean_scores, to_uint8
from stages.scoring.visuals import colour_depth, contact_sheet, error_image
from plenoxels.core.cameras import Intrinsics
from plenoxels.core.scene_model import SceneModel
from stages.settings.evaluate import Settings
from stages.common.layout import METRICS_JSON, MODEL_JSON, SCENE_JSON



def _spread(items: list, limit: int) -> list:
    if limit <= 0 or len(items) <= limit:
        return items
    return [items[i] for i in np.linspace(0, len(items) - 1, limit).round().astype(int)]


def run(ctx) -> dict:
    s: Settings = ctx.settings
    scene = read_json(ctx.upstream["normalize"] / SCENE_JSON)
    model = SceneModel.load(ctx.upstream["fit"])
    fit_record = read_json(ctx.upstream["fit"] / MODEL_JSON)
    scale = float(fit_record.get("fit_settings", {}).get("image_scale", 1.0)) if s.scale == "fit" else float(s.scale)
    frames = scene.get("frames") or []
    held_out = _spread([f for f in frames if f.get("split") == "test"], s.max_views)
    train = [f for f in frames if f.get("split", "train") == "train"] or frames

    # Where the photos' gains follow the order they were taken in, not where they scatter (PhotoGains.follows_order).
    in_neighbours_colour = model.photo_gains is not None and model.photo_gains.follows_order
    # And where the light across their frames follows it too (PhotoGains.fields_follow_order).
    in_neighbours_light = model.photo_gains is not None and model.photo_gains.fields_follow_order
    for folder in ("renders", "gt", "depth"):
        (ctx.work / folder).mkdir()
    views, sheet_rows, captions = [], [], []
    with_lpips = bool(held_out) and weights_available()
    if held_out and not with_lpips:
        ctx.report.warn("LPIPS not scored: its weights are not installed; run `make install`")
    sheet_names = {f["name"] for f in _spread(held_out, s.sheet_rows)}
    started = time.monotonic()
    for frame in ctx.report.track(held_out, desc="rendering held-out views"):
        truth, k, mask = read_frame(ctx.out, frame, scale, model.background_color)
        with torch.no_grad():
            # A photo with a backdrop of its own colour is scored with that colour past the grid, as it was fitted.
            out = model.render_camera(np.asarray(frame["transform_matrix"], dtype=np.float64), k,
                                      backdrop=frame.get("backdrop"), photo=frame["name"])
        render = out["rgb"].cpu().numpy().astype(np.float32)
        gain = model.photo_gains.of(frame["name"]) if in_neighbours_colour else None
        views.append({"name": frame["name"], "width": k.w, "height": k.h, **image_scores(render, truth, with_lpips),
                      **(masked_scores(render, truth, mask) if mask is not None else {}),
                      **({"gain": [round(float(g), 4) for g in gain]} if gain is not None else {})})
        write_png(ctx.work / "renders" / f"{frame['name']}.png", to_uint8(render))
        write_png(ctx.work / "gt" / f"{frame['name']}.png", to_uint8(truth))
        write_png(ctx.work / "depth" / f"{frame['name']}.png",
                  colour_depth(out["depth"].cpu().numpy(), out["opacity"].cpu().numpy()))
        if frame["name"] in sheet_names:
            sheet_rows.append((to_uint8(truth), to_uint8(render), error_image(render, truth)))
            captions.append(_caption(views[-1]))
    render_seconds = time.monotonic() - started
    if sheet_rows:
        write_png(ctx.work / "contact_sheet.png", contact_sheet(sheet_rows, s.sheet_side, captions))

    video = None
    if s.video_frames:
        path_kind, path = default_path(scene, train, s.video_frames, ndc=model.fit_frame.ndc is not None)
        k = median_intrinsics(train, s.video_side)
        # Even sizes: H.264 in yuv420p needs them.
        k = Intrinsics(k.fl_x, k.fl_y, k.cx - (k.w % 2) / 2, k.cy - (k.h % 2) / 2, k.w - k.w % 2, k.h - k.h % 2)
        with imageio.get_writer(ctx.work / "video.mp4", fps=s.video_fps, codec="libx264", quality=7,
                                macro_block_size=1) as writer:
            for c2w in ctx.report.track(path, desc=f"rendering the {path_kind} video"):
                with torch.no_grad():
                    writer.append_data(to_uint8(model.render_camera(c2w, k)["rgb"].cpu().numpy()))
        video = {"file": "video.mp4", "path": path_kind, "frames": s.video_frames, "width": k.w, "height": k.h,
                 "fps": s.video_fps}

    mean = mean_scores(views)
    write_json(ctx.work / METRICS_JSON, {"views": views, "mean": mean, "scale": scale, "count": len(views),
                                           "render_seconds": round(render_seconds, 2), "video": video,
                                           "colour": ("capture neighbours' gains across the frame" if in_neighbours_light
                                                      else "capture neighbours' gains" if in_neighbours_colour
                                                      else "common"),
                                           "ssim": "skimage.metrics.structural_similarity, gaussian, data_range 1",
                                           "lpips": "AlexNet, v0.1 (stages/scoring/lpips.py)" if with_lpips else None})
    if mean:
        lpips = f", LPIPS {mean['lpips']:.3f}" if "lpips" in mean else ""
        line = (f"PSNR {mean['psnr']:.2f} dB, SSIM {mean['ssim']:.3f}{lpips} on {len(views)} held-out views "
                f"at {views[0]['width']}x{views[0]['height']}")
        if in_neighbours_light:
            line += " (each in the colour and light across the frame of its neighbours in the capture)"
        elif in_neighbours_colour:
            line += " (each in the colour of its neighbours in the capture)"
        if "psnr_masked" in mean:
            line += f"; inside their masks PSNR {mean['psnr_masked']:.2f} dB, SSIM {mean['ssim_masked']:.3f}"
    else:
        line = "no held-out views to score (normalize.holdout_every=0)"
    if video:
        line += f"; {video['path']} video of {video['frames']} frames"
    return {"line": line, "views": len(views), "psnr": mean["psnr"] if mean else None,
            "ssim": mean["ssim"] if mean else None, "lpips": mean.get("lpips") if mean else None,
            "psnr_masked": mean.get("psnr_masked") if mean else None}


def _caption(view: dict) -> str:
    lpips = f"  LPIPS {view['lpips']:.3f}" if "lpips" in view else ""
    return f"{view['name']}: PSNR {view['psnr']:.2f} dB  SSIM {view['ssim']:.3f}{lpips}"
