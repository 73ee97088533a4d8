"""Benchmark of the exported splats on scenes already run through export: for each splat cap, the splats fitted as the
export stage fits them (plenoxels/splats/field_splats.py), scored on held-out views against the photos and the field
(stages/scoring/splat_views.py), and their files' sizes beside the textured mesh's GLB.

Goal: the splats' held-out PSNR within 1 dB of the field's on the same views, splats.ply and splats.glb no larger
than 10x mesh.glb.

    .venv/bin/python -m bench.splats OUT [OUT ...] [--caps 500000,100000] [--seconds 120] [--views 8]
Writes bench/results/splats.json (or splats-<label>.json with --label).
"""
from __future__ import annotations

import argparse
import os
import tempfile
import time
from pathlib import Path

from bench.common import recorded
from bench.fit import machine
from stages.common.json_files import read_json, write_json
from stages.interchange.splat_files import write_splat_glb, write_splat_ply
from stages.scoring.splat_views import score_splats
from stages.settings.export import Settings
from plenoxels.core.scene_model import SceneModel
from plenoxels.splats.field_splats import fit_splats

GOAL_DB = 1.0
GOAL_SIZE_RATIO = 10.0


def measure(out: Path, cap: int, seconds: float, views: int) -> dict:
    scene = read_json(out / "normalize" / "scene.json")
    fitted = SceneModel.load(out / "fit")
    model = fitted.foreground_model()
    s = Settings()
    started = time.time()
    splats, record = fit_splats(model, scene["frames"], cap, s.splat_min_weight, s.splat_scale, s.splat_views, seconds,
                                s.splat_window, s.seed)
    fit_seconds = time.time() - started
    scale = float(read_json(out / "fit" / "model.json").get("fit_settings", {}).get("image_scale", 1.0))
    held = score_splats(out, splats, fitted, scene["frames"], scale, views)
    with tempfile.TemporaryDirectory() as folder:
        write_splat_ply(Path(folder) / "s.ply", splats)
        write_splat_glb(Path(folder) / "s.glb", splats)
        sizes = {name: (Path(folder) / name).stat().st_size for name in ("s.ply", "s.glb")}
    mesh = out / "export" / "mesh.glb"
    mesh_bytes = mesh.stat().st_size if mesh.is_file() else None
    gap = held["field_psnr"] - held["psnr"] if held.get("views") else None
    return {"scene": out.name, "cap": cap, "count": splats.count, "grid_splats": record["grid_splats"],
            "background_splats": record["background_splats"], "distillation": record["distillation"],
            "fit_seconds": round(fit_seconds, 1), "held_out": held, "below_field_db": round(gap, 3) if gap is not None else None,
            "ply_bytes": sizes["s.ply"], "glb_bytes": sizes["s.glb"], "mesh_glb_bytes": mesh_bytes,
            "size_ratio": round(max(sizes.values()) / mesh_bytes, 2) if mesh_bytes else None,
            "goal_met": gap is not None and gap <= GOAL_DB and bool(mesh_bytes)
                        and max(sizes.values()) <= GOAL_SIZE_RATIO * mesh_bytes}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("outs", nargs="+", type=Path, help="scene output folders with fit/ and export/")
    parser.add_argument("--caps", default="500000", help="comma-separated export.max_splats values")
    parser.add_argument("--seconds", type=float, default=Settings().splat_seconds, help="distillation seconds")
    parser.add_argument("--views", type=int, default=Settings().splat_score_views, help="held-out views scored")
    parser.add_argument("--label", default="")
    args = parser.parse_args()
    runs = []
    for out in args.outs:
        for cap in (int(c) for c in args.caps.split(",")):
            runs.append(measure(out, cap, args.seconds, args.views))
            r = runs[-1]
            print(f"{r['scene']} cap {cap}: {r['count']} splats, PSNR {r['held_out'].get('psnr')} dB vs the field's "
                  f"{r['held_out'].get('field_psnr')} dB, PLY {r['ply_bytes'] / 1e6:.1f} MB, GLB {r['glb_bytes'] / 1e6:.1f} "
                  f"MB, {r['size_ratio']}x mesh.glb", flush=True)
    name = f"splats-{args.label}.json" if args.label else "splats.json"
    write_json(Path(__file__).parent / "results" / name,
               {"recorded": recorded(), "machine": machine(), "threads": os.environ.get("OMP_NUM_THREADS"),
                "load_average_at_end": [round(x, 2) for x in os.getloadavg()], "seconds": args.seconds,
                "goal": {"db": GOAL_DB, "size_ratio": GOAL_SIZE_RATIO}, "runs": runs})


if __name__ == "__main__":
    main()
