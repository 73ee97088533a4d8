"""What a fit of the fit stage read and how it ended, and what it says of itself: fit.json's record and the stage's
summary line (stages/fit.py runs the fit; these describe it)."""
from __future__ import annotations

import time
from dataclasses import dataclass

import torch

from plenoxels.core.train import Fitter
from plenoxels.core.photo_colour import PhotoGains
from plenoxels.core.ray_set import RaySet
from plenoxels.planning import model_trial
from plenoxels.planning.budget import TimeBudget
from stages.common.text import format_bytes, format_count, format_duration
from stages.training.views import HeldOut


@dataclass
class FitInputs:
    """What each fit of the stage reads: the scene, its training rays and held-out views, and the model trial's choice."""
    scene: dict
    train: RaySet
    train_names: list[str]  # the training photos' names, in the RaySet's order
    held_out: HeldOut
    seen: HeldOut           # training views rendered as the held-out ones are
    device: torch.device
    started: float          # time.monotonic() the stage started at; the time budget counts from it
    choice: dict            # model_trial.choose's record


@dataclass
class Ending:
    """How a fit ended, for its record and summary."""
    resumed_from: int
    stopped_early: bool = False     # by Ctrl-C: the model as it stands
    at_deadline: bool = False       # by the time budget: a normal end
    background_why: str = ""        # why a background model was added ("" when it was not)


def photo_gains(fitter: Fitter, inputs: FitInputs, across_frames: bool = False) -> PhotoGains | None:
    """The photos' colours as the fit measured them (None where it took the photos as they are): a held-out photo's
    in its capture neighbours' colour. `across_frames`: with each photo's gains across its frame, measured now (the
    fit's end: Fitter.gain_fields)."""
    if not fitter.fits_colour:
        return None
    fields = fitter.gain_fields() if across_frames else None
    return PhotoGains([f["name"] for f in inputs.scene.get("frames") or []],
                      dict(zip(inputs.train_names, fitter.colour.gain.tolist())), fitter.backdrop_as_taken,
                      None if fields is None else dict(zip(inputs.train_names, fields.numpy())))


def fit_record(fitter: Fitter, inputs: FitInputs, ending: Ending, budget: TimeBudget | None,
               final_psnr: float | None, seen_psnr: float | None) -> dict:
    """fit.json: what ran, what it made and what it cost. `train_psnr` is the running PSNR of the last batches (where
    error-drawn rays seek what is still wrong, it reads low), `train_views_psnr` the training views rendered whole as
    the held-out ones are."""
    s = fitter.options
    schedule, model = fitter.schedule, fitter.model
    memory = model.memory_bytes()
    record = {
        "complete": not ending.stopped_early,
        "resolutions": schedule.resolutions, "steps_per_level": schedule.steps,
        "steps": fitter.step, "total_steps": schedule.total_steps, "resumed_from_step": ending.resumed_from,
        "seconds": round(fitter.elapsed, 1), "device": str(inputs.device),
        "train_images": len(fitter.train), "train_pixels": fitter.train.num_pixels,
        "train_psnr": round(fitter.train_psnr(), 3),
        "train_views_psnr": round(seen_psnr, 3) if seen_psnr is not None else None,
        "train_views": len(inputs.seen.views),
        "held_out_psnr": round(final_psnr, 3) if final_psnr is not None else None,
        "held_out_views": len(inputs.held_out.views), "held_out_scale": s.eval_scale,
        "history": fitter.history, "levels": fitter.levels, "converged": fitter.converged,
        "model": model.describe(),
        "memory_bytes": memory,
        "regularisation": fitter.regularisation,
        "photo_colour": fitter.colour_record(),
        "transients": (fitter.error_map.transients_record()
                       if fitter.error_map is not None and fitter.options.leave_out_transients else None),
        "background_added": ending.background_why or None,
        "scene_model": model_trial.model_name(model), "model_choice": inputs.choice or {},
        "own_backdrops": fitter.train.backdrops is not None and model.background is None,
        "empty_backdrop": fitter.empty_backdrop,
        "covered_backdrop_share": fitter.options.covered_backdrop_share if fitter.empty_backdrop else 0.0,
        "clipped_floors": round(fitter.train.clipped_share(), 4),
    }
    if inputs.device.type == "cpu":
        used, available = fitter.grad.threads()
        record["gradient_threads"] = {"used": used, "available": available}
    if fitter.bg_optim is not None:
        optimiser_bytes = sum(t.numel() * t.element_size() for t in (fitter.bg_optim.grad, fitter.bg_optim.second_moment))
        # On a CPU the grid's loss draws the spheres in its own pass: the seconds are then its backward and optimiser.
        record["background_cost"] = {"seconds": round(fitter.background_seconds, 2),
                                     "share_of_fitting": round(fitter.background_seconds / max(fitter.elapsed, 1e-9), 4),
                                     "drawn_in_the_grids_pass": inputs.device.type == "cpu",
                                     "model_bytes": memory["background"], "optimiser_bytes": optimiser_bytes}
    if budget is not None:
        record["budget"] = budget.record(ending.at_deadline)
        record["budget"]["stage_seconds"] = round(time.monotonic() - budget.started, 1)
    return record


def summary(ctx, fitter: Fitter, inputs: FitInputs, ending: Ending, record: dict, final_psnr: float | None,
            seen_psnr: float | None) -> str:
    """The stage's summary line: the grid, its PSNRs and time, the model's parts and advice where the fit overfits."""
    s = fitter.options
    model, held_out, choice = fitter.model, inputs.held_out, inputs.choice or {}
    grid = model.grid
    res = grid.resolution
    shape = f"{res[0]}^3" if len(set(res)) == 1 else "x".join(map(str, res))
    line = f"{shape} grid"
    coarsening = grid.coarsening() if grid.warped else 1.0
    if coarsening >= 1.05:   # a surroundings box just past the foreground has cells of one size
        line += f" (cells up to {coarsening:.3g}x coarser around the foreground)"
    line += f", {format_count(grid.num_occupied)} voxels ({format_bytes(record['memory_bytes']['total'])})"
    # Quick estimates (a few views, downscaled); the evaluate stage gives the full held-out figure.
    if seen_psnr is not None:
        line += f", train PSNR ~{seen_psnr:.1f} dB ({len(inputs.seen.views)} training views at {s.eval_scale:g}x)"
    else:
        line += f", train PSNR {record['train_psnr']:.1f} dB (its last batches)"
    if final_psnr is not None:
        line += f", held-out ~{final_psnr:.1f} dB ({len(held_out.views)} views at {s.eval_scale:g}x)"
    line += f", {format_duration(fitter.elapsed)}"
    if fitter.converged is not None:
        c = fitter.converged
        line += (f", the last level converged (train PSNR {c['gain_db']:+.3f} dB over its latest {c['window']} steps, "
                 f"under {s.converged_db:g}): ended {c['steps_saved']} steps early")
    if model.background is not None:
        cost = record["background_cost"]
        line += (f", background model {format_bytes(cost['model_bytes'] + cost['optimiser_bytes'])} with its optimiser, "
                 f"{cost['share_of_fitting']:.0%} of the fitting time"
                 + (" training it (drawn in the grid's pass)" if cost.get("drawn_in_the_grids_pass") else ""))
        if ending.background_why:
            line += f" (added: {ending.background_why})"
    if choice.get("chosen") or choice.get("questions"):
        line += "; " + model_trial.summary(choice)
    line += fitter.regularisation_summary() + fitter.colour_summary()
    if (transients := record["transients"]) and transients["photos"]:
        line += (f", {transients['share']:.1%} of the photos' pixels left out, in {transients['photos']} of "
                 f"{len(fitter.train)} (what moved between them)")
    threads = record.get("gradient_threads")
    if threads and threads["used"] < threads["available"]:
        line += (f", gradients on {threads['used']} of {threads['available']} "
                 f"threads (a gradient table per thread would pass their share of the memory)")
    if record["own_backdrops"]:
        line += ", each photo's own backdrop colour past the grid"
    if record["empty_backdrop"]:
        line += ", random backdrops where the masks are empty"
        if record.get("covered_backdrop_share"):
            line += f" and behind {record['covered_backdrop_share']:.0%} of the rays they cover"
    if record["clipped_floors"] >= 0.001:
        line += f", clipped highlights ({record['clipped_floors']:.1%} of pixels) trained as floors"
    if model.fit_frame.ndc is not None:
        line += ", in NDC"
    if model.fit_frame.contraction is not None:
        line += ", contracted (all of space)"
    if not ending.stopped_early and seen_psnr is not None and final_psnr is not None:
        advice = model_trial.gap_advice(seen_psnr, final_psnr, record["scene_model"], choice,
                                        record["regularisation"].get("views_per_point"))
        if advice:
            ctx.report.warn(advice.removeprefix("; "))
            line += advice
    return line


def budget_summary(fitter: Fitter, ending: Ending, budget: TimeBudget | None) -> str:
    """How the fit ended, for the summary line: a stop by Ctrl-C, the time budget's plan and what ran."""
    schedule, line = fitter.schedule, ""
    if ending.stopped_early:
        line += f"; stopped early at step {fitter.step}/{schedule.total_steps} (Ctrl-C)"
    if budget is not None:
        ran = f"ran {'->'.join(map(str, schedule.resolutions))}, {'+'.join(map(str, schedule.steps))} steps"
        line += f"; {budget.line()}; " + (f"stopped at the deadline at step {fitter.step}/{schedule.total_steps}"
                                         if ending.at_deadline else ran)
    return line
