"""Peers in the same run: TensoRF fitting lego on this CPU beside our fit, and the time each needs to reach the
other's held-out PSNR.

The protocol: lego's 100 training photos at 200x200, the first 25 val views held out (lego here has no test split),
both sides scored by one function against the same truth: each RGBA val photo composited onto white and resized
with area averaging, as the evaluate stage does.

TensoRF (Chen et al. 2022; pure PyTorch, the fastest peer that trains on a CPU) runs from a checkout of its
repository, nothing in it changed: its lego config (TensorVMSplit, 30000 steps planned, batches of 4096 rays) with
`downsample_train 4`, its own training loop, on this environment's CPU torch and every core, for --minutes of
training. Its loop calls its evaluation hook every step here; the hook is replaced by one that renders the held-out
views with TensoRF's renderer once the training clock passes each of --checkpoints, and stops the loop after the
last. The clock starts at the loop (the photos' loading and the model's set-up are not counted) and pauses while
the hook scores. The modules TensoRF imports only for logging, depth pictures and mesh export (tensorboard,
plyfile, scikit-image) are stood in for by empty ones, torchvision's ToTensor by the same conversion; it needs
configargparse (its options) and kornia (its rays), which leave this environment's torch as it is.

Ours: the `fast` preset and time budgets on `default`'s detail (--budgets), at image scale 0.25, each the fit stage
as the pipeline runs it, photos loaded inside its time, in a process of its own (bench/fit.py's runs).

    git clone https://github.com/apchenstu/TensoRF bench/out/peers/TensoRF    # once (or pass --tensorf)
    .venv/bin/pip install configargparse kornia                                # once
    .venv/bin/python -m bench.peers                                             # 10 minutes of TensoRF, then ours
    .venv/bin/python -m bench.peers --minutes 0.5 --checkpoints 15 30 --budgets 5s --results bench/out/peers.json
"""
from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
import types
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))

from plenoxels.core.errors import UserError  # noqa: E402

RESULTS = REPO / "bench" / "results" / "peers.json"
WORK = REPO / "bench" / "out" / "peers"
CHECKOUT = WORK / "TensoRF"
SCALE = 0.25  # 800x800 -> 200x200
VIEWS = 25
BUDGETS = ("5s", "12s", "30s")
MISSING = ("bench.peers: skipped: needs a TensoRF checkout (git clone https://github.com/apchenstu/TensoRF "
           "bench/out/peers/TensoRF, or pass --tensorf) and configargparse and kornia "
           "(.venv/bin/pip install configargparse kornia)")


def protocol_data(lego: Path, folder: Path) -> Path:
    """`folder`, made afresh, as TensoRF's Blender loader reads it: lego's train split and, as its `test` split, the
    first VIEWS val views, each photo at 200x200 as our fit and scoring see it (composited onto white,
    area-averaged), written opaque. TensoRF's loader sizes its rays by downsample_train but reads the photos at full
    size (it resets its own factor before the resize), so the photos must already be at the protocol's size.
    Nothing under `lego` is written: `folder` is emptied first, so no link left in it can lead a write there."""
    import shutil

    import imageio.v3 as iio
    import numpy as np

    from bench.cuda import blender_frames
    from stages.common.frames import load_frame

    if folder.is_symlink() or folder.is_file():
        folder.unlink()
    elif folder.exists():
        shutil.rmtree(folder)  # removes links inside it, never what they point to
    for split, name, limit in (("train", "train", None), ("val", "test", VIEWS)):
        meta = json.loads((lego / f"transforms_{split}.json").read_text())
        meta["frames"] = meta["frames"][:limit]
        (folder / split).mkdir(parents=True)
        for frame in blender_frames(lego, split)[:limit]:
            rgb = load_frame(lego, frame, SCALE, np.ones(3, dtype=np.float32))[0]
            opaque = np.concatenate([rgb, np.ones_like(rgb[..., :1])], axis=-1)
            iio.imwrite(folder / frame["file_path"], np.round(opaque * 255).astype(np.uint8))
        (folder / f"transforms_{name}.json").write_text(json.dumps(meta))
    return folder


def to_tensor(image):
    """torchvision's ToTensor for the 8-bit photos TensoRF reads: [H,W,C] bytes to [C,H,W] floats in [0, 1]."""
    import numpy as np
    import torch

    return torch.from_numpy(np.asarray(image, dtype=np.float32) / 255.0).permute(2, 0, 1).contiguous()


def stand_ins() -> None:
    """Empty modules for what TensoRF imports only to log, draw depth and export meshes, and torchvision's one
    conversion it uses (torchvision pins a torch of its own)."""
    class SummaryWriter:
        def __init__(self, *args, **kwargs):
            pass

        def add_scalar(self, *args, **kwargs):
            pass

    def module(name: str, **attributes) -> None:
        sys.modules[name] = types.ModuleType(name)
        sys.modules[name].__dict__.update(attributes)

    module("torch.utils.tensorboard", SummaryWriter=SummaryWriter)
    module("torchvision")
    module("torchvision.transforms", ToTensor=lambda: to_tensor)
    sys.modules["torchvision"].transforms = sys.modules["torchvision.transforms"]
    module("plyfile")
    module("skimage")
    module("skimage.measure")
    sys.modules["skimage"].measure = sys.modules["skimage.measure"]


class Finished(Exception):
    """Raised from the evaluation hook after the last checkpoint: TensoRF's loop has no other way out."""


def tensorf_run(spec: dict) -> dict:
    """TensoRF's training loop on lego until the last of spec["checkpoints"] (training seconds), with its held-out
    PSNR at each."""
    import numpy as np
    import torch

    from bench.cuda import blender_frames
    from stages.common.frames import load_frame
    from stages.scoring.metrics import image_psnr

    checkout, lego = Path(spec["checkout"]), Path(spec["lego"])
    val = blender_frames(lego, "val")[:VIEWS]  # the views protocol_data wrote as TensoRF's test split
    truths = [load_frame(lego, frame, SCALE, np.ones(3, dtype=np.float32))[0] for frame in val]
    stand_ins()
    sys.path.insert(0, str(checkout))
    import train  # TensoRF's train.py
    from opt import config_parser

    marks = sorted(spec["checkpoints"])
    clock = {"start": None, "paused": 0.0}
    curve = []

    class ClockedSampler(train.SimpleSampler):
        def __init__(self, *args, **kwargs):
            if clock["start"] is None:  # the loop starts right after the first sampler
                clock["start"] = time.perf_counter()
            super().__init__(*args, **kwargs)

    def checkpoint(test_dataset, tensorf, args, renderer, save_path=None, N_vis=5, prtx="", N_samples=-1,  # noqa: N803
                   white_bg=False, ndc_ray=False, compute_extra_metrics=True, device=None):
        now = time.perf_counter()
        trained = now - clock["start"] - clock["paused"]
        if trained < marks[0]:
            return [0.0]
        if len(test_dataset.all_rays) != len(truths):
            raise UserError(f"TensoRF read {len(test_dataset.all_rays)} held-out views where the protocol has "
                            f"{len(truths)}; are lego's val photos all on disk?")
        while marks and marks[0] <= trained:
            marks.pop(0)
        psnrs = []
        with torch.no_grad():
            for rays, truth in zip(test_dataset.all_rays, truths):
                rgb = renderer(rays.view(-1, rays.shape[-1]), tensorf, chunk=4096, N_samples=N_samples,
                               ndc_ray=ndc_ray, white_bg=white_bg, device=torch.device("cpu"))[0]
                psnrs.append(image_psnr(rgb.clamp(0, 1).reshape(truth.shape).numpy(), truth))
        curve.append({"seconds": round(trained, 1), "steps": int(prtx.rstrip("_")) + 1,
                      "psnr": float(np.mean(psnrs)), "scoring_seconds": round(time.perf_counter() - now, 1)})
        print(f"  TensoRF: {curve[-1]['psnr']:.2f} dB after {trained:.0f} s of training, "
              f"{curve[-1]['steps']} steps", file=sys.stderr, flush=True)
        clock["paused"] += time.perf_counter() - now
        if not marks:
            raise Finished
        return psnrs

    train.SimpleSampler = ClockedSampler
    train.evaluation = checkpoint
    with tempfile.TemporaryDirectory(prefix="bench-peers-") as logs:
        args = config_parser(["--config", str(checkout / "configs" / "lego.txt"), "--datadir", spec["data"],
                              "--basedir", logs, "--downsample_train", str(round(1 / SCALE)), "--vis_every", "1",
                              "--N_vis", "-1", "--render_test", "0", "--progress_refresh_rate", "1000000"])
        torch.set_default_dtype(torch.float32)
        torch.manual_seed(20211202)  # TensoRF's own seeds
        np.random.seed(20211202)
        try:
            train.reconstruction(args)
        except Finished:
            pass
    if not curve:
        raise UserError("TensoRF ran no checkpoint; give --minutes past the first --checkpoints")
    commit = subprocess.run(["git", "-C", str(checkout), "rev-parse", "HEAD"], capture_output=True, text=True)
    return {"curve": curve, "threads": torch.get_num_threads(), "config": "configs/lego.txt",
            "commit": commit.stdout.strip() or None}


def ours(args) -> list[dict]:
    """`fast` and the time budgets at 200x200, scored on the same views (bench/fit.py's runs)."""
    from bench import fit

    plan_args = argparse.Namespace(scenes=["lego"], presets=["fast"], knobs=["budget"], budgets=args.budgets,
                                   base=dict(fit.SWEEP_BASE), eval_scale=SCALE, val_limit=VIEWS)
    runs = []
    for spec in fit.plan(plan_args, {"image_scale": SCALE}):
        result = fit.spawn({**spec, "data": str(args.data), "verbose": False})
        if result is not None:
            print(f"  ours, {spec['label']}: {result['psnr']:.2f} dB in {result['fit_seconds']:.1f} s", flush=True)
            runs.append({"label": spec["label"], "psnr": result["psnr"], "seconds": result["fit_seconds"],
                         "summary": result["summary"]})
    return runs


def first_reaching(points: list[dict], psnr: float) -> dict | None:
    """The earliest point (by seconds) at `psnr` or above."""
    reached = [p for p in points if p["psnr"] >= psnr]
    return min(reached, key=lambda p: p["seconds"]) if reached else None


def crossings(tensorf_curve: list[dict], our_runs: list[dict]) -> dict:
    """The time each side needs to reach the other's PSNR: ours to TensoRF's last checkpoint, and TensoRF to each of
    our runs (None where it did not within its run)."""
    last = max(tensorf_curve, key=lambda p: p["seconds"])
    ours_first = first_reaching(our_runs, last["psnr"])
    return {
        "tensorf_final": last,
        "ours_to_tensorf_final": None if ours_first is None else {
            **ours_first, "share_of_tensorf_time": ours_first["seconds"] / last["seconds"]},
        "tensorf_to_ours": [{"label": run["label"], "psnr": run["psnr"],
                             "tensorf_seconds": (hit or {}).get("seconds")}
                            for run in our_runs for hit in [first_reaching(tensorf_curve, run["psnr"])]],
    }


def summary(results: dict) -> str:
    c = results["crossings"]
    last = c["tensorf_final"]
    lines = [f"TensoRF: {last['psnr']:.2f} dB after {last['seconds']:.0f} s of training ({last['steps']} steps)"]
    mine = c["ours_to_tensorf_final"]
    lines.append("ours: never reached it" if mine is None else
                 f"ours reach it in {mine['seconds']:.1f} s ({mine['label']}: {mine['psnr']:.2f} dB), "
                 f"1/{1 / mine['share_of_tensorf_time']:.0f} of TensoRF's time")
    for row in c["tensorf_to_ours"]:
        lines.append(f"TensoRF to ours' {row['label']} ({row['psnr']:.2f} dB): " +
                     ("not within its run" if row["tensorf_seconds"] is None else f"{row['tensorf_seconds']:.0f} s"))
    return "\n".join(lines)


def run_both(args) -> int:
    from bench.common import run_child
    from bench.fit import machine
    from stages.common.text import parse_duration

    checkout = args.tensorf.resolve()
    if not (checkout / "train.py").is_file() or not (checkout / "configs" / "lego.txt").is_file():
        print(MISSING)
        return 0
    try:
        import configargparse  # noqa: F401
        import kornia  # noqa: F401
    except ImportError:
        print(MISSING)
        return 0
    if not (args.data / "lego" / "transforms_val.json").is_file():
        raise UserError(f"no lego scene under {args.data}; pass --data (the folder that holds lego/)")
    if args.checkpoints and max(args.checkpoints) > args.minutes * 60:
        raise UserError("--checkpoints must lie within --minutes")
    for budget in args.budgets:
        parse_duration(budget, "--budgets")
    checkpoints = sorted(set(args.checkpoints) | {args.minutes * 60})
    print(f"TensoRF on lego 200x200 for {args.minutes:g} minutes of training", flush=True)
    spec = {"checkout": str(checkout), "lego": str((args.data / "lego").resolve()),
            "data": str(protocol_data(args.data / "lego", WORK / "lego-200x200")), "checkpoints": checkpoints}
    tensorf = run_child("bench.peers", spec, "TensoRF")
    if tensorf is None:
        return 1
    print("ours on the same views", flush=True)
    our_runs = ours(args)
    if not our_runs:
        return 1
    results = {"machine": machine(), "finished": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
               "protocol": {"scene": "lego", "size": [200, 200], "held_out": f"the first {VIEWS} val views",
                            "tensorf_minutes": args.minutes},
               "tensorf": tensorf, "ours": our_runs, "crossings": crossings(tensorf["curve"], our_runs)}
    args.results.parent.mkdir(parents=True, exist_ok=True)
    args.results.write_text(json.dumps(results, indent=1) + "\n")
    print(summary(results))
    print(f"wrote {args.results}")
    return 0


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--one", action="store_true", help=argparse.SUPPRESS)
    parser.add_argument("--data", type=Path, default=REPO.parent / "shared" / "data")
    parser.add_argument("--tensorf", type=Path, default=CHECKOUT, help="a checkout of apchenstu/TensoRF")
    parser.add_argument("--minutes", type=float, default=10.0, help="TensoRF's training time")
    parser.add_argument("--checkpoints", type=float, nargs="*", default=[],
                        help="training seconds at which TensoRF's held-out PSNR is also taken, besides at --minutes "
                             "(each costs 1.5-12 minutes of scoring on 2 cores: least once its grid has emptied)")
    parser.add_argument("--budgets", nargs="+", default=list(BUDGETS), help="our time budgets")
    parser.add_argument("--results", type=Path, default=RESULTS, help="the JSON to write")
    args = parser.parse_args(argv)
    from bench.common import run_part

    return run_part(args, tensorf_run, run_both)


if __name__ == "__main__":
    sys.exit(main())
