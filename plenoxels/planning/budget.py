"""A time budget for one fit: the pacer that keeps it on time.

`TimeBudget` calibrates the machine (plenoxels/planning/fit_cost.py), chooses the fit's levels, resolutions and steps
(plenoxels/planning/fit_plan.py), and, attached to the Fitter, measures what the real scene costs as the fit goes: its step
times, level changes, what each prune keeps and its held-out renders. Every REPLAN_EVERY steps and at each level
change it re-plans the steps of the levels under way and to come (dropping a level that cannot get half its steps,
bringing a dropped one back when the costs measured since fit it, raising a last level to come that would get more
than MAX_SHARE of its steps, and lowering a last level too dear for half of them), and it says when the fit must
stop so that the stage ends by the deadline with a complete model.
"""
from __future__ import annotations

import dataclasses
import functools
import json
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch

from plenoxels.planning.fit_cost import calibrate
from plenoxels.planning.fit_plan import (COARSE_LAST, FINE_MIN_SHARE, FINEST_MAX_SHARE, FIRST_KEEP_PRIOR, LADDER,
                                         MAX_SHARE, MIN_SHARE, FitFacts, Plan, Rung, began_upsampled, change_seconds,
                                         choose, finest_worth, finish_seconds, ladder_at, replan, upsample_band)
from plenoxels.core.memory import voxels_that_fit
from plenoxels.core.scene_model import SceneModel
from plenoxels.core.schedule import Schedule
from plenoxels.core.train import Fitter, pruning_rays
from plenoxels.core.ray_set import RaySet

# Re-plan every this many steps; a level's step time is the mean of its latest STEP_WINDOW, after its first few.
REPLAN_EVERY = 20
STEP_WINDOW = 100
LEVEL_WARMUP = 3
# Re-plans aim this share of the budget short of the deadline, so that noise in the step times ends the schedule
# before the deadline's stop does (which would cut the last level's learning-rate decay short).
SLACK = 0.02
# A calibration measured for a budget (the first on a machine, its code or options new) has this share of the budget:
# past it, the finer points wait for a longer budget (fit_cost.measure). A whole one took 4.6 s on bench/README's
# 2-core machine B (2026-11-30), a sixth of a 30 s budget, and 33 s there while it ran twice its cores' work.
CALIBRATION_SHARE = 0.25


@dataclasses.dataclass
class BudgetClock:
    """The time a fit has, from when, and where its plan is kept so that a resumed fit keeps it."""
    seconds: float
    started: float                  # time.monotonic() the budget counts from
    plan_file: Path | None = None
    resume: bool = False            # the fit resumes from a checkpoint: keep the plan saved in plan_file


class TimeBudget:
    """Plans a fit to end by its clock's `started + seconds` and keeps it on time.

    Made before the Fitter, which then runs on its `schedule` (the plan's levels and steps, re-planned as the fit
    goes), and `attach`ed to it once it exists (resumed or new). While it runs, the caller calls `step()` after each step and
    `level()` after each level change, wraps held-out evaluations in `timed`, and stops the fit when `due()`.
    `line()` says what was chosen and why; `record()` says it all, for fit.json.
    """

    def __init__(self, clock: BudgetClock, options, new_model: Callable[[int], SceneModel], train: RaySet,
                 eval_rays: int, device: torch.device, say: Callable[[str], None] | None = None,
                 ladder: tuple[Rung, ...] | None = None):
        """`new_model(resolution)` makes the fit's first model (its box and background are what a plan needs)."""
        self.seconds, self.started, self.plan_file = float(clock.seconds), clock.started, clock.plan_file
        plan_file, resume = clock.plan_file, clock.resume
        self.deadline = self.started + self.seconds
        ladder = ladder_at(options.first_level_scale, ladder or LADDER)
        probe = new_model(8)  # an 8^3 grid: kept, as its shape at each resolution sets a pruning pass's rays
        firsts = {rung.resolutions[0] for rung in ladder}
        box_voxels = {r: int(np.prod(probe.resolution_for(r))) for r in firsts}
        background = probe.background.config() if probe.background is not None else None
        self.facts = FitFacts(box_voxels=box_voxels.__getitem__, eval_rays=eval_rays,
                              prune_rays=functools.lru_cache(maxsize=None)(
                                  lambda r: pruning_rays(train.sizes, max(probe.resolution_for(r)), options)),
                              eval_every=options.eval_every, checkpoint_every=options.checkpoint_every,
                              voxel_budget=min(options.voxel_budget, voxels_that_fit(options.sh_degree)),
                              max_resolution=int(train.sizes.max()),
                              first_keep=FIRST_KEEP_PRIOR[probe.scene_type],
                              fine_min_share=MIN_SHARE if background is None or probe.grid.contracted
                              else FINE_MIN_SHARE, prune_upsampled=options.prune_upsampled)
        background = background and {"n_spheres": background["n_spheres"], "width": background["width"]}
        self.costs, self.calibration = calibrate(options, device, background, say=say,
                                                allowance=CALIBRATION_SHARE * self.left())
        saved = json.loads(plan_file.read_text()) if resume and plan_file is not None and plan_file.is_file() else None
        if saved is not None:  # a resumed fit keeps the plan its checkpoint was made with
            self.rung = Rung(tuple(saved["rung"]["resolutions"]), tuple(saved["rung"]["steps"]),
                             saved["rung"].get("fixed", 0))
            self.plan = Plan(**saved["plan"])
            resolutions, steps = saved["resolutions"], saved["steps"]
        else:
            self.plan = choose(self.left(), self.costs, self.facts, ladder)
            self.rung = next(r for r in ladder if list(r.resolutions) == self.plan.resolutions)
            resolutions, steps = self.plan.resolutions, self.plan.steps
        self.schedule = Schedule(list(resolutions), list(steps))
        self.now = self.facts.outlook()
        self.fitter: Fitter | None = None
        self.replans: list[dict] = []          # at each level change, and the latest one within each level
        self.level_seconds: list[float] = []   # the step time measured at each level
        self._intervals: list[float] = []      # the current level's latest step times
        self._last = time.perf_counter()
        self._eval_seconds = 0.0               # of held-out evaluations since the last step
        self._save_plan()

    def left(self) -> float:
        return self.deadline - time.monotonic()

    def attach(self, fitter: Fitter) -> None:
        """Follows `fitter` from here; a resumed fit has already used `fitter.elapsed` of the budget, and its level
        changes have measured what its prunes keep."""
        self.fitter = fitter
        self.facts.finish_rays = fitter.gain_field_rays
        self.deadline = self.started + self.seconds - fitter.elapsed
        start = sum(self.schedule.steps[:fitter.level])
        self.schedule.steps[fitter.level] = max(self.schedule.steps[fitter.level], fitter.step - start)
        resolutions = self.schedule.resolutions
        self.now = self.facts.outlook(level=fitter.level, step=fitter.step, voxels=fitter.model.grid.num_occupied,
                                      dense=not fitter.levels)
        for level, entry in enumerate(fitter.levels):
            self.now.kept(self._keep_measured(level + 1), _kept_share(entry))
            if entry.get("upsampled") and self.facts.prune_upsampled:
                self.now.upsample_band = upsample_band(entry["occupied"] / entry["upsampled"],
                                                       resolutions[level + 1] / resolutions[level])
        self._last = time.perf_counter()

    def due(self) -> bool:
        """True when what is left of the budget is what it takes to end the fit as it stands (the stop's checkpoint,
        the last pruning pass, the held-out PSNR and the save)."""
        resolution = self.schedule.resolutions[self.fitter.level]
        return self.left() <= finish_seconds(self.costs, self.facts, self.now, resolution, self.now.voxels, stop=True)

    def step(self) -> None:
        """After each step: its time (held-out evaluations left out), and a re-plan every REPLAN_EVERY steps."""
        clock = time.perf_counter()
        interval, self._last, self._eval_seconds = clock - self._last - self._eval_seconds, clock, 0.0
        if self.fitter.step - sum(self.schedule.steps[:self.fitter.level]) > LEVEL_WARMUP:
            self._intervals = (self._intervals + [interval])[-STEP_WINDOW:]
        if self.fitter.step % REPLAN_EVERY == 0 and len(self._intervals) >= 5:
            measured = float(np.mean(self._intervals))
            ratio = measured / self.costs.step_seconds(self.now.voxels, dense=self.now.dense)
            # A grid at the first resolution, pruned early or not, is still clearing its air, so its steps speak of
            # its own level, not of the machine: its ratio only counts above the calibration as measured. It may undo
            # a retime that read the machine slower than its steps now run (a stall while it was timed), not call it
            # faster. What it says of the finer levels after it, fit_plan.predict decides.
            self.now.ratio_at_first = self._at_first_resolution()
            floor = 1.0 / max(1.0, self.calibration.get("slower_now") or 1.0)
            self.now.step_ratio = max(floor, ratio) if self.now.ratio_at_first else ratio
            self.now.step_seconds = measured
            self._replan("steps")

    def level(self) -> None:
        """After a level change: what it took, the share pruning kept, the new grid; then a re-plan."""
        fitter = self.fitter
        change, self._eval_seconds = time.perf_counter() - self._last - self._eval_seconds, 0.0
        entry = fitter.levels[-1]
        before, after = self.schedule.resolutions[fitter.level - 1], self.schedule.resolutions[fitter.level]
        predicted = change_seconds(self.costs, self.facts, before, after, entry.get("upsampled") or entry["occupied"],
                                   entry["occupied"])
        self.now.change_ratio = change / max(predicted, 1e-9)
        self.now.kept(self._keep_measured(fitter.level), _kept_share(entry))
        if entry.get("upsampled") and self.facts.prune_upsampled:
            self.now.upsample_band = upsample_band(entry["occupied"] / entry["upsampled"], after / before)
        if self._intervals:
            self.level_seconds.append(round(float(np.mean(self._intervals)), 5))
        self.now.level, self.now.voxels, self.now.dense = fitter.level, entry["occupied"], False
        self.now.step_seconds = None
        self._intervals = []
        self._last = time.perf_counter()
        self._replan("level change")

    def timed(self, evaluate: Callable[[SceneModel], float]) -> Callable[[SceneModel], float]:
        """`evaluate` (a held-out evaluation), timed: kept out of the step times, and what later ones will take."""
        def run(model: SceneModel) -> float:
            begun = time.perf_counter()
            value = evaluate(model)
            took = time.perf_counter() - begun
            self._eval_seconds += took
            if self.facts.eval_rays:
                self.now.eval_ratio = took / max(self.costs.pass_seconds(self.facts.eval_rays,
                                                                         max(model.grid.resolution)), 1e-9)
            return value
        return run

    def _keep_measured(self, level: int) -> str:
        """The Outlook share that the prune at the change to `level` measures: the first prune's, that of a level
        which began as an upsample pruned on its own render (fit.prune_upsampled), or a later prune's."""
        if level == 1:
            return "first_keep"
        settled = self.facts.prune_upsampled and began_upsampled(self.schedule.resolutions, level)
        return "settled_keep" if settled else "later_keep"

    def _at_first_resolution(self) -> bool:
        """Whether the fit is still at its first level's resolution (its early-pruned rest included)."""
        return self.schedule.resolutions[self.fitter.level] == self.schedule.resolutions[0]

    def _replan(self, why: str) -> None:
        self.now.step = self.fitter.step
        # The plan's levels that an earlier re-plan dropped stay candidates: a level dropped on costs predicted before
        # its resolution was reached comes back once the steps measured since leave time for it (else the fit ends
        # early, its last level at twice its steps).
        kept = len(self.schedule.resolutions)
        candidates = self.schedule.resolutions + self.plan.resolutions[kept:]
        resolutions, steps, share = replan(self.left() - SLACK * self.seconds, self.costs, self.facts, self.now,
                                           self.rung, candidates, self.schedule.steps + self.plan.steps[kept:],
                                           measured=not self._at_first_resolution())
        entry = {"why": why, "step": self.fitter.step, "seconds_left": round(self.left(), 1), "share": round(share, 3),
                 "steps": steps, "step_seconds": round(self.now.step_seconds or 0.0, 5), "voxels": self.now.voxels,
                 "step_ratio": round(self.now.step_ratio, 3)}
        if len(resolutions) < kept:
            entry["dropped_levels"] = self.schedule.resolutions[len(resolutions):]
        elif len(resolutions) > kept:
            entry["restored_levels"] = resolutions[kept:]
        elif resolutions[-1] != self.schedule.resolutions[-1]:
            moved = "raised" if resolutions[-1] > self.schedule.resolutions[-1] else "lowered"
            entry[f"{moved}_last_level"] = [self.schedule.resolutions[-1], resolutions[-1]]
        # The fitter consults this schedule at every step (Fitter.run).
        self.schedule.resolutions[:] = resolutions
        self.schedule.steps[:] = steps
        # A steps-only re-plan replaces the one before it, unless either dropped, restored, raised or lowered a level
        # (that stays in the record).
        changed_levels = {"dropped_levels", "restored_levels", "raised_last_level", "lowered_last_level"}
        if (why == "steps" and self.replans and self.replans[-1]["why"] == "steps"
                and not changed_levels & (set(entry) | set(self.replans[-1]))):
            self.replans[-1] = entry
        else:
            self.replans.append(entry)
        self._save_plan()

    def _save_plan(self) -> None:
        if self.plan_file is None:
            return
        state = {"rung": dataclasses.asdict(self.rung), "plan": dataclasses.asdict(self.plan),
                 "resolutions": self.schedule.resolutions, "steps": self.schedule.steps}
        tmp = self.plan_file.with_name(self.plan_file.name + ".tmp")
        tmp.write_text(json.dumps(state))
        tmp.replace(self.plan_file)

    # ---- what it says -----------------------------------------------------------------------------------------
    def line(self) -> str:
        """'budget 90s: 2 levels 96->192, 600+900 steps, predicted 84 s from a calibration of ... on this machine'."""
        note = ""
        if not self.plan.fits:
            note = " (less than the coarsest plan needs: it stops at the deadline)"
        elif self.plan.share >= FINEST_MAX_SHARE and finest_worth(self.plan.resolutions[-1],
                                                                   self.facts.max_resolution, LADDER):
            note = (f" (as fine as the {self.facts.max_resolution}-pixel photos are worth, with {FINEST_MAX_SHARE:g}x "
                    f"the steps: it ends early)")
        slower = self.calibration.get("slower_now")
        cached = (f" (cached, scaled by {slower:.2f} to the machine's speed now)"
                  if self.calibration["cached"] and slower else "")
        if self.calibration.get("partial"):
            cached += (f" (partial: its finer points past {CALIBRATION_SHARE:g} of the budget wait for a longer "
                       f"one)")
        return (f"budget {_duration(self.seconds)}: {self.plan.describe()}, predicted {self.plan.predicted:.0f} s"
                f"{note} from a calibration of {self.costs.describe()}{cached} on this machine")

    def record(self, stopped_at_deadline: bool) -> dict:
        latest = [round(float(np.mean(self._intervals)), 5)] if self._intervals else []
        return {
            "seconds": self.seconds, "line": self.line(),
            "why": (f"the finest candidate (plenoxels/planning/fit_plan.py LADDER) no finer than the photos' "
                    f"{self.facts.max_resolution} pixels whose predicted time fits with at least {MIN_SHARE:g}x its "
                    f"steps ({self.facts.fine_min_share:g}x ending finer than {COARSE_LAST}^3), given the most steps "
                    f"that fit, up to {MAX_SHARE:g}x ({FINEST_MAX_SHARE:g}x where no finer grid can take the time)"),
            "chosen": {**dataclasses.asdict(self.plan), "share": round(self.plan.share, 3),
                       "predicted": round(self.plan.predicted, 1)},
            "ran": {"resolutions": list(self.schedule.resolutions), "steps": list(self.schedule.steps)},
            "stopped_at_deadline": stopped_at_deadline,
            "step_seconds_per_level": self.level_seconds + latest,
            "scene_over_model": {"later_steps": round(self.now.step_ratio, 3),
                                 "level_change": round(self.now.change_ratio, 3),
                                 "held_out": round(self.now.eval_ratio, 3)},
            "kept_share": {"first_prune": round(self.now.first_keep, 4), "later_prunes": round(self.now.later_keep, 4),
                           "first_prune_prior": self.facts.first_keep,
                           **({"settled_prunes": round(self.now.settled_keep, 4),
                               "upsampled_grids": [round(e["occupied"] / e["upsampled"], 4)
                                                   for e in self.fitter.levels if e.get("upsampled")],
                               "upsampled_band": round(self.now.upsample_band, 4)}
                              if self.facts.prune_upsampled else {})},
            "replans": self.replans,
            "calibration": {"costs": dataclasses.asdict(self.costs), "points": self.calibration.get("points"),
                            "first_level_points": self.calibration.get("first_level_points"),
                            "passes": self.calibration.get("passes"),
                            "level_change": self.calibration.get("level_change"),
                            "cached": self.calibration["cached"], "file": self.calibration["file"],
                            "slower_now": self.calibration.get("slower_now"),
                            "retimed": self.calibration.get("retimed"),
                            "key": self.calibration["key"], "measured_in_seconds": self.calibration.get("seconds"),
                            "partial": self.calibration.get("partial", False),
                            "allowance": self.calibration.get("allowance"),
                            "load_average": self.calibration.get("load_average"),
                            "when": self.calibration.get("when")},
        }


def _kept_share(level_change: dict) -> float:
    """The share of the grid's voxels a level change's prune kept (one of Fitter.levels)."""
    return level_change["kept"] / max(1, level_change["pruned_from"])


def _duration(seconds: float) -> str:
    """90 -> '1m30s', 300 -> '5m', 45 -> '45s'."""
    minutes, rest = divmod(int(round(seconds)), 60)
    return f"{minutes}m{rest:02d}s" if minutes and rest else f"{minutes}m" if minutes else f"{rest}s"
