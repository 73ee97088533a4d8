"""Fit: the training photos of normalize/scene.json -> a Plenoxels sparse voxel grid, coarse to fine.

Reads the train split only (held-out frames are used for the live held-out PSNR, never for fitting).
Images with a mask are composited onto `background_color`, so what lies outside the masks is fitted as empty (a
masked capture's photos without a mask are left out: stages/training/views.py). An object fit with nothing but that
colour behind its grid that cannot reproduce its own photos by the end of its coarsest resolution starts again with a
background model, and its summary says why. The model is made by
plenoxels.core.scene_model.SceneModel.create and trained by plenoxels.core.train.Fitter (batches, schedules,
pruning and upsampling between levels are described there).

Writes fit/grid.pt and fit/model.json (SceneModel.save) and fit/fit.json (the levels, occupied voxels,
memory, losses and held-out PSNR over time, timings).

With `time_budget` the levels, resolutions and steps are not the settings' but a plan made by
plenoxels.planning.budget.TimeBudget to end the stage within the budget (from a cost model measured on this
machine, then the fit's own measured cost); a stop at its deadline is a normal end (`complete: true`).

Interruptions:
- a checkpoint is written to the stage's scratch folder every `checkpoint_every` seconds and at each
  level change; a re-run with the same inputs and settings resumes from it (same step, same batches);
- the first Ctrl-C stops the fit after the current step and writes the model as it stands as the
  fit's output (`complete: false` in fit.json, "stopped early" in the summary), so the later stages
  run from it. That output stands for these settings: change a setting or use `--force fit` to fit
  again from the start. A second Ctrl-C aborts at once, keeping the checkpoint;
- if the loss or a parameter becomes NaN or infinite the fit stops with a message naming the setting
  to lower; the last checkpoint (always written from finite parameters) stays in the scratch folder.
"""
from __future__ import annotations

import time
from dataclasses import replace

from stages.common.interrupts import StopRequest
from stages.common.json_files import read_json, write_json
from stages.common.text import format_bytes, format_count, format_duration
from stages.training.views import HeldOut, load_training, training_frames
from plenoxels.planning.budget import TimeBudget
from plenoxels.planning import model_trial
from plenoxels.core.errors import UserError
from plenoxels.core.native import resolve_device
from plenoxels.core.scene_model import BACKDROP_MIN_TRAIN_PSNR, SceneModel, backdrop_check_step
from plenoxels.core.train import Diverged, Fitter, RaySet, Schedule
from stages.settings.fit import Settings
from stages.common.layout import CHECKPOINT_PT, FIT_JSON, SCENE_JSON

BUDGET_PLAN = "budget_plan.json"
BACKGROUND_ADDED = "background_added.json"
MODEL_TRIAL = "model_trial.json"


def run(ctx) -> dict:
    started = time.time()
    s: Settings = ctx.settings
    device = resolve_device(s.device)
    if device.type != "cpu":
        ctx.report.info(f"fitting on {device}")
    scene = read_json(ctx.upstream["normalize"] / SCENE_JSON)
    train_frames, held_out_frames = training_frames(scene, ctx.report)
    train = load_training(ctx.out, train_frames, s.image_scale, s.background_color, ctx.report)
    held_out = HeldOut(ctx.out, held_out_frames, s.eval_views, s.eval_scale, s.background_color)
    # Training views rendered as the held-out ones are, so that the gap between the two compares like with like.
    seen = HeldOut(ctx.out, train_frames, s.eval_views, s.eval_scale, s.background_color)
    # Where normalize's measures leave the model open, short coarse fits of each plausible one choose it (inside the
    # time budget, which counts from `started`).
    s, choice = model_trial.choose(scene, s, train, device, s.budget_seconds, ctx.scratch / MODEL_TRIAL, ctx.report.info)
    added = ctx.scratch / BACKGROUND_ADDED
    while True:
        # An object fit whose photos' backdrop is no one colour starts again with a background model (see fit()).
        fitted = fit(ctx, s, scene, train, held_out, seen, device, started,
                     read_json(added)["why"] if added.is_file() else "", choice)
        if fitted is not None:
            return fitted


def fit(ctx, settings: Settings, scene: dict, train: RaySet, held_out: HeldOut, seen: HeldOut, device, started: float,
        background_why: str, choice: dict) -> dict | None:
    """Fits the model and finishes the stage; None where an object fit with one colour behind its grid cannot
    reproduce its own photos at the end of its coarsest resolution (scene_model.backdrop_check_step): what surrounds
    the object is not that colour, so the reason is kept in the scratch folder and the caller fits again with a
    background model."""
    s: Settings = replace(settings, background="on") if background_why else settings
    checkpoint = ctx.scratch / CHECKPOINT_PT
    mean_colour = train.mean_colour()

    def new_model(resolution: int) -> SceneModel:
        return SceneModel.create(scene, s, resolution, focal_px=float(train.k[:, :2].median()), mean_colour=mean_colour)

    budget = None
    if s.budget_seconds:
        budget = TimeBudget(s.budget_seconds, s, new_model, train, held_out.rays, device, started,
                            plan_file=ctx.scratch / BUDGET_PLAN, resume=checkpoint.is_file(), say=ctx.report.info)
        ctx.report.info(budget.line())
    schedule = budget.schedule if budget is not None else Schedule.for_fit(s)
    fitter = Fitter(new_model(schedule.resolutions[0]), s, train, device, schedule)
    masked = any(f.get("mask_path") for f in scene.get("frames", []))
    check_step = None if masked or s.background != "auto" else backdrop_check_step(fitter.model, schedule.resolutions,
                                                                                   schedule.steps)
    backdrop_psnr: list[float] = []

    if checkpoint.is_file():
        fitter.load_checkpoint(checkpoint)
        ctx.report.info(f"resuming from the checkpoint at step {fitter.step}/{schedule.total_steps}")
    resumed_from = fitter.step
    if budget is not None:
        budget.attach(fitter)

    def on_level(grid) -> None:
        if budget is not None:
            budget.level()
        ctx.report.info(f"level {fitter.level + 1}: {'x'.join(map(str, grid.resolution))} grid, "
                        f"{format_count(grid.num_occupied)} voxels ({format_bytes(grid.memory_bytes())})")

    def on_eval(entry: dict) -> None:
        ctx.report.info(f"step {entry['step']}: held-out PSNR {entry['held_out_psnr']:.2f} dB")

    evaluate = held_out.psnr if budget is None else budget.timed(held_out.psnr)
    try:
        with StopRequest() as stop, ctx.report.bar(total=schedule.total_steps, desc="fitting") as bar:
            bar.update(fitter.step)

            def on_step(mse: float) -> None:
                if budget is not None:
                    budget.step()
                    bar.total = schedule.total_steps
                bar.update(1)
                bar.set_postfix(loss=f"{mse:.4f}", psnr=f"{fitter.train_psnr():.2f}", refresh=False)

            def stop_requested() -> bool:
                if fitter.step == check_step and fitter.train_psnr() < BACKDROP_MIN_TRAIN_PSNR:
                    backdrop_psnr.append(fitter.train_psnr())
                    return True
                return stop.requested or (budget is not None and budget.due())

            stopped = fitter.run(checkpoint, s.checkpoint_every, stop_requested=stop_requested,
                                 held_out_psnr=evaluate if held_out else None, eval_every=s.eval_every,
                                 on_step=on_step, on_level=on_level, on_eval=on_eval)
    except Diverged as exc:
        kept = (f"the last good checkpoint (step {fitter.checkpoint_step}) is kept"
                if fitter.checkpoint_step is not None else "no checkpoint was written yet")
        raise UserError(f"the fit diverged at step {fitter.step} ({exc}); lower fit.lr_density (now {s.lr_density:g}) "
                        f"or fit.lr_sh (now {s.lr_sh:g}) and run again; {kept}") from None
    if backdrop_psnr:
        why = (f"train PSNR {backdrop_psnr[0]:.1f} dB at step {fitter.step} (below {BACKDROP_MIN_TRAIN_PSNR:g} dB): what "
               "surrounds the object is not the one colour behind the grid, so a background model shows it")
        ctx.report.warn(f"{why}; fitting again with it")
        checkpoint.unlink(missing_ok=True)
        (ctx.scratch / BUDGET_PLAN).unlink(missing_ok=True)
        write_json(ctx.scratch / BACKGROUND_ADDED, {"why": why})
        return None
    stopped_early = stopped and stop.requested
    at_deadline = stopped and not stop.requested
    if stopped_early:
        ctx.report.warn(f"stopped early at step {fitter.step}/{schedule.total_steps} (Ctrl-C); writing the model as "
                        f"it stands")
    elif at_deadline and s.prune_final:
        fitter.prune()  # the time budget's deadline: the end of the fit, pruned as a complete schedule is
    return finish(ctx, fitter, held_out, resumed_from, stopped_early, device, budget, at_deadline, background_why,
                  choice, seen)


def finish(ctx, fitter: Fitter, held_out: HeldOut, resumed_from: int, stopped_early: bool, device,
           budget: TimeBudget | None = None, at_deadline: bool = False, background_why: str = "",
           choice: dict | None = None, seen: HeldOut | None = None) -> dict:
    s: Settings = fitter.options
    schedule = fitter.schedule
    model = fitter.model
    final_psnr = held_out.psnr(model) if held_out else None
    memory = model.memory_bytes()
    model.save(ctx.work, extra={"fit_settings": {"resolutions": schedule.resolutions, "steps": schedule.steps,
                                                 **{k: getattr(s, k) for k in ("sh_degree", "image_scale", "step_size")}}})
    grid = model.grid
    record = {
        "complete": not stopped_early,
        "resolutions": schedule.resolutions, "steps_per_level": schedule.steps,
        "steps": fitter.step, "total_steps": schedule.total_steps, "resumed_from_step": resumed_from,
        "seconds": round(fitter.elapsed, 1), "device": str(device),
        "train_images": len(fitter.train), "train_pixels": fitter.train.num_pixels,
        "train_psnr": round(fitter.train_psnr(), 3),
        "held_out_psnr": round(final_psnr, 3) if final_psnr is not None else None,
        "held_out_views": len(held_out.views), "held_out_scale": s.eval_scale,
        "history": fitter.history, "levels": fitter.levels,
        "model": model.describe(),
        "memory_bytes": memory,
        "regularisation": fitter.regularisation,
        "background_added": background_why or None,
        "scene_model": model_trial.model_name(model), "model_choice": choice or {},
        "own_backdrops": fitter.train.backdrops is not None and model.background is None,
    }
    if device.type == "cpu":
        used, available = fitter.grad.threads()
        record["gradient_threads"] = {"used": used, "available": available}
    if fitter.bg_optim is not None:
        optimiser_bytes = sum(t.numel() * t.element_size() for t in (fitter.bg_optim.grad, fitter.bg_optim.second_moment))
        record["background_cost"] = {"seconds": round(fitter.background_seconds, 2),
                                     "share_of_fitting": round(fitter.background_seconds / max(fitter.elapsed, 1e-9), 4),
                                     "model_bytes": memory["background"], "optimiser_bytes": optimiser_bytes}
    if budget is not None:
        record["budget"] = budget.record(at_deadline)
        record["budget"]["stage_seconds"] = round(time.time() - budget.started, 1)
    write_json(ctx.work / FIT_JSON, record)
    res = grid.resolution
    shape = f"{res[0]}^3" if len(set(res)) == 1 else "x".join(map(str, res))
    line = (f"{shape} grid, {format_count(grid.num_occupied)} voxels ({format_bytes(memory['total'])}), "
            f"train PSNR {record['train_psnr']:.1f} dB")
    if final_psnr is not None:
        # A quick estimate (a few views, downscaled); the evaluate stage gives the full figure.
        line += f", held-out ~{final_psnr:.1f} dB ({len(held_out.views)} views at {s.eval_scale:g}x)"
    line += f", {format_duration(fitter.elapsed)}"
    if model.background is not None:
        cost = record["background_cost"]
        line += (f", background model {format_bytes(cost['model_bytes'] + cost['optimiser_bytes'])} with its optimiser, "
                 f"{cost['share_of_fitting']:.0%} of the fitting time")
        if background_why:
            line += f" (added: {background_why})"
    if (choice or {}).get("chosen"):
        line += "; " + model_trial.summary(choice)
    line += fitter.regularisation_summary()
    if "gradient_threads" in record and record["gradient_threads"]["used"] < record["gradient_threads"]["available"]:
        line += (f", gradients on {record['gradient_threads']['used']} of {record['gradient_threads']['available']} "
                 f"threads (a gradient table per thread would pass their share of the memory)")
    if record["own_backdrops"]:
        line += ", each photo's own backdrop colour past the grid"
    if model.fit_frame.ndc is not None:
        line += ", in NDC"
    if model.fit_frame.contraction is not None:
        line += ", contracted (all of space)"
    if not stopped_early and seen and final_psnr is not None:
        advice = model_trial.gap_advice(seen.psnr(model), final_psnr, record["scene_model"], choice or {},
                                        record["regularisation"].get("views_per_point"))
        if advice:
            ctx.report.warn(advice.removeprefix("; "))
            line += advice
    if stopped_early:
        line += f"; stopped early at step {fitter.step}/{schedule.total_steps} (Ctrl-C)"
    if budget is not None:
        ran = f"ran {'->'.join(map(str, schedule.resolutions))}, {'+'.join(map(str, schedule.steps))} steps"
        line += f"; {budget.line()}; " + (f"stopped at the deadline at step {fitter.step}/{schedule.total_steps}"
                                         if at_deadline else ran)
    return {"line": line, "complete": not stopped_early, "steps": fitter.step, "occupied": grid.num_occupied,
            "train_psnr": record["train_psnr"], "held_out_psnr": record["held_out_psnr"],
            "seconds": record["seconds"], "memory_bytes": memory["total"]}
