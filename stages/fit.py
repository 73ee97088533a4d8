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
from stages.common.text import format_bytes, format_count
from stages.training.fit_record import Ending, FitInputs, budget_summary, fit_record, photo_gains, summary
from stages.training.views import HeldOut, load_training, training_frames
from plenoxels.planning.budget import BudgetClock, TimeBudget
from plenoxels.planning import model_trial
from plenoxels.planning.fit_plan import photo_scale
from plenoxels.core.errors import UserError
from plenoxels.core.native import resolve_device
from plenoxels.core.scene_model import BACKDROP_MIN_TRAIN_PSNR, SceneModel, backdrop_check_step
from plenoxels.core.schedule import Schedule
from plenoxels.core.train import Diverged, Fitter
from stages.settings.fit import Settings
from stages.common.layout import CHECKPOINT_PT, FIT_JSON, SCENE_JSON

BUDGET_PLAN = "budget_plan.json"
BACKGROUND_ADDED = "background_added.json"
MODEL_TRIAL = "model_trial.json"


def run(ctx) -> dict:
    started = time.monotonic()
    s: Settings = ctx.settings
    device = resolve_device(s.device)
    if device.type != "cpu":
        ctx.report.info(f"fitting on {device}")
    scene = read_json(ctx.upstream["normalize"] / SCENE_JSON)
    train_frames, held_out_frames = training_frames(scene, ctx.report)
    if s.budget_seconds:
        s = budget_photo_scale(s, train_frames, ctx.report)
    train = load_training(ctx.out, train_frames, s.image_scale, s.background_color, ctx.report,
                          with_masks=s.photo_colour, with_cover=s.empty_backdrop, with_clipped=s.clipped_floors)
    held_out = HeldOut(ctx.out, held_out_frames, s.eval_views, s.eval_scale, s.background_color)
    # Training views rendered as the held-out ones are, so that the gap between the two compares like with like.
    seen = HeldOut(ctx.out, train_frames, s.eval_views, s.eval_scale, s.background_color)
    # Where normalize's measures leave the model open, short coarse fits of each plausible one choose it (inside the
    # time budget, which counts from `started`).
    s, choice = model_trial.choose(scene, s, train, device, s.budget_seconds, ctx.scratch / MODEL_TRIAL, ctx.report.info)
    inputs = FitInputs(scene, train, [f["name"] for f in train_frames], held_out, seen, device, started, choice)
    fitted = fit(ctx, s, inputs, background_added(ctx))
    if fitted is None:  # an object fit whose photos' backdrop is no one colour: again, with a background model
        fitted = fit(ctx, s, inputs, background_added(ctx))
    return fitted


def budget_photo_scale(s: Settings, train_frames: list[dict], report) -> Settings:
    """The settings with the share of their size a time budget fits the photos at (fit_plan.photo_scale): more than
    image_scale where that would leave them coarser than the preset's own finest grid."""
    longest = max((max(int(f["w"]), int(f["h"])) for f in train_frames), default=0)
    scale = photo_scale(longest, s.image_scale, s.resolutions[-1])
    if scale <= s.image_scale:
        return s
    report.info(f"photos at {scale:.2f} of their size, not fit.image_scale's {s.image_scale:g}: {round(longest * scale)} "
                f"pixels, as fine as the preset's own {s.resolutions[-1]}^3 grid, which the budget's grid may then reach")
    return replace(s, image_scale=round(scale, 4))


def background_added(ctx) -> str:
    """Why an earlier fit of these inputs added a background model ("" when none did)."""
    added = ctx.scratch / BACKGROUND_ADDED
    return read_json(added)["why"] if added.is_file() else ""


def fit(ctx, settings: Settings, inputs: FitInputs, background_why: str) -> dict | None:
    """Fits the model and finishes the stage; None where an object fit with one colour behind its grid cannot
    reproduce its own photos at the end of its coarsest resolution (scene_model.backdrop_check_step): what surrounds
    the object is not that colour, so the reason is kept in the scratch folder and the caller fits again with a
    background model (a fit with one is never checked so, so it does not return None)."""
    s: Settings = replace(settings, background="on") if background_why else settings
    checkpoint = ctx.scratch / CHECKPOINT_PT
    fitter, budget, check_step = start(ctx, s, inputs, checkpoint)
    resumed_from = fitter.step
    how, backdrop_psnr = train_levels(ctx, fitter, inputs, budget, check_step, checkpoint)
    if how == "backdrop":
        why = (f"train PSNR {backdrop_psnr:.1f} dB at step {fitter.step} (below {BACKDROP_MIN_TRAIN_PSNR:g} dB): what "
               "surrounds the object is not the one colour behind the grid, so a background model shows it")
        ctx.report.warn(f"{why}; fitting again with it")
        checkpoint.unlink(missing_ok=True)
        (ctx.scratch / BUDGET_PLAN).unlink(missing_ok=True)
        write_json(ctx.scratch / BACKGROUND_ADDED, {"why": why})
        return None
    if how == "ctrl-c":
        ctx.report.warn(f"stopped early at step {fitter.step}/{fitter.schedule.total_steps} (Ctrl-C); writing the "
                        f"model as it stands")
    elif how == "deadline" and s.prune_final:
        fitter.prune()  # the time budget's deadline: the end of the fit, pruned as a complete schedule is
    return finish(ctx, fitter, inputs, Ending(resumed_from, how == "ctrl-c", how == "deadline", background_why), budget)


def start(ctx, s: Settings, inputs: FitInputs, checkpoint) -> tuple[Fitter, TimeBudget | None, int | None]:
    """The fit's Fitter on its schedule (a time budget's plan when the settings give one, which then follows the
    Fitter), resumed from the checkpoint when there is one, and the step at which an object fit with one colour behind
    its grid checks that it reproduces its photos (None where it does not: a masked capture, a model set by hand)."""
    train, mean_colour = inputs.train, inputs.train.mean_colour()

    def new_model(resolution: int) -> SceneModel:
        return SceneModel.create(inputs.scene, s, resolution, focal_px=float(train.k[:, :2].median()),
                                 mean_colour=mean_colour)

    budget = None
    if s.budget_seconds:
        clock = BudgetClock(s.budget_seconds, inputs.started, plan_file=ctx.scratch / BUDGET_PLAN,
                            resume=checkpoint.is_file())
        budget = TimeBudget(clock, s, new_model, train, inputs.held_out.rays, inputs.device, say=ctx.report.info)
        ctx.report.info(budget.line())
    schedule = budget.schedule if budget is not None else Schedule.for_fit(s)
    fitter = Fitter(new_model(schedule.resolutions[0]), s, train, inputs.device, schedule)
    masked = any(f.get("mask_path") for f in inputs.scene.get("frames", []))
    # The schedule as planned, before a resumed fit's budget stretches the level under way.
    check_step = None if masked or s.background != "auto" else backdrop_check_step(fitter.model, schedule.resolutions,
                                                                                   schedule.steps)
    if checkpoint.is_file():
        try:
            fitter.load_checkpoint(checkpoint)
            ctx.report.info(f"resuming from the checkpoint at step {fitter.step}/{schedule.total_steps}")
        except Exception as e:  # cut short or damaged on disk: torch and pickle raise many kinds
            checkpoint.unlink()
            ctx.report.info(f"the checkpoint could not be read ({type(e).__name__}); starting the fit afresh")
            fitter = Fitter(new_model(schedule.resolutions[0]), s, train, inputs.device, schedule)
    if budget is not None:
        budget.attach(fitter)
    return fitter, budget, check_step


def train_levels(ctx, fitter: Fitter, inputs: FitInputs, budget: TimeBudget | None, check_step: int | None,
                 checkpoint) -> tuple[str, float | None]:
    """Runs the fit to the end of its schedule; returns how it ended ("complete", "ctrl-c", "deadline" or "backdrop":
    its train PSNR at `check_step` too low for one colour behind the grid, with that PSNR)."""
    s: Settings = fitter.options
    schedule, held_out, backdrop_psnr = fitter.schedule, inputs.held_out, []

    def on_level(grid) -> None:
        if budget is not None:
            budget.level()
        ctx.report.info(f"level {fitter.level + 1}: {'x'.join(map(str, grid.resolution))} grid, "
                        f"{format_count(grid.num_occupied)} voxels ({format_bytes(grid.memory_bytes())})")

    def on_eval(entry: dict) -> None:
        ctx.report.info(f"step {entry['step']}: held-out PSNR {entry['held_out_psnr']:.2f} dB")

    def held_out_psnr(model) -> float:
        model.photo_gains = photo_gains(fitter, inputs)  # the photos' colours as measured so far
        return held_out.psnr(model)

    evaluate = held_out_psnr if budget is None else budget.timed(held_out_psnr)
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
        return "backdrop", backdrop_psnr[0]
    if not stopped:
        return "complete", None
    return ("ctrl-c" if stop.requested else "deadline"), None


def finish(ctx, fitter: Fitter, inputs: FitInputs, ending: Ending, budget: TimeBudget | None) -> dict:
    """Saves the model, writes fit.json and returns the stage's result with its summary line."""
    s: Settings = fitter.options
    schedule, model, held_out = fitter.schedule, fitter.model, inputs.held_out
    model.photo_gains = photo_gains(fitter, inputs, across_frames=True)
    final_psnr = held_out.psnr(model) if held_out else None
    seen_psnr = inputs.seen.psnr(model) if inputs.seen else None
    model.save(ctx.work, extra={"fit_settings": {"resolutions": schedule.resolutions, "steps": schedule.steps,
                                                 **{k: getattr(s, k) for k in ("sh_degree", "image_scale", "step_size")}}})
    record = fit_record(fitter, inputs, ending, budget, final_psnr, seen_psnr)
    write_json(ctx.work / FIT_JSON, record)
    line = summary(ctx, fitter, inputs, ending, record, final_psnr, seen_psnr) + budget_summary(fitter, ending, budget)
    return {"line": line, "complete": not ending.stopped_early, "steps": fitter.step,
            "occupied": model.grid.num_occupied, "train_psnr": record["train_psnr"],
            "train_views_psnr": record["train_views_psnr"],
            "held_out_psnr": record["held_out_psnr"], "seconds": record["seconds"],
            "memory_bytes": record["memory_bytes"]["total"]}
