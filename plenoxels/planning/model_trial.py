"""Which scene model explains a capture, chosen by evidence where normalize's proxies are not clear-cut.

Normalize types a scene from measures taken before any fitting (stages/framing/scene_frame.py): the spread of the viewing
directions, the share of sparse points far beyond the foreground, the share of pixels that show an empty backdrop.
Near their thresholds more than one model is plausible, and the proxies cannot tell which one the photos need (a can
on a tiled floor just past the contraction threshold made normalize contract all of space, which lost the can in
held-out views that a bounded grid with background spheres kept). There the fit asks the photos: each
plausible model fits a few training photos on one short coarse level, renders training photos it did not fit, and the
better held-out PSNR wins, by at least MARGIN_DB over the model the proxies picked (a coarse level's scores differ
between seeds, so a small lead is noise; the proxies' pick is kept on a tie).

The questions, each a pair of models (MODELS):
- NDC or the world frame: the viewing directions spread within normalize.borderline_deg of the forward limit
  (scene.json's `measured.borderline`; normalize then writes the forward block too, so NDC can be tried);
- a contracted grid or a bounded grid with background spheres: an unbounded scene whose share of points beyond the
  foreground lies in CONTRACT_BAND times normalize's threshold, or that has no points to measure it;
- one colour behind a bounded grid (an object) or background spheres: either backdrop proxy (points beyond, empty
  pixels) within BACKDROP_BAND times its threshold, photos without masks.
A capture none of them asks about is clear-cut and costs nothing. A model set by hand (fit.ndc, fit.contract,
fit.background, normalize.scene_type) is never second-guessed. The winner is fitted with the settings of the scene
type normalize gave (its configs/scene_types overlay: TV, the first level's scale, the voxel cap), as the trial was.
"""
from __future__ import annotations

import json
import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
import torch

from plenoxels.core.scene_model import SceneModel, psnr, reaches_far
from plenoxels.core.schedule import Schedule
from plenoxels.core.train import Fitter
from plenoxels.core.ray_set import RaySet

# The models a trial chooses between, by the fit's toggles that make each.
MODELS: dict[str, dict[str, str]] = {
    "ndc": {"ndc": "on", "contract": "off", "background": "off"},
    "contracted": {"ndc": "off", "contract": "on", "background": "off"},
    "bounded + background": {"ndc": "off", "contract": "off", "background": "on"},
    "bounded": {"ndc": "off", "contract": "off", "background": "off"},
}
# Where a proxy is not clear-cut, as multiples of its threshold: the share of points beyond the foreground for the
# contraction (a room that a bounded grid holds has few points beyond; a street or a landscape has most of them
# there), and both backdrop proxies for an object against background spheres.
CONTRACT_BAND = (0.25, 5.0)
BACKDROP_BAND = (0.5, 2.0)
# Another model replaces the proxies' pick only when its held-out PSNR is at least this much higher.
MARGIN_DB = 0.3
# The trial's level: the fit's first resolution (its coarse start), no finer than MAX_RESOLUTION, of STEPS steps of the
# fit's batches, pruned after a fifth of them. Coarser than the fit's own first level, a trial ranks models by what
# they show at a resolution no fit ends at, and can rank them the wrong way round (a contracted grid's floaters near
# the cameras need the finer cells to show; bench/README.md).
MAX_RESOLUTION = 64
STEPS = 300
# Training photos held out of the trial's fits to score them: this many at most, evenly spread through the photos by
# name (an orbit's photos follow each other, so they see the scene from around it), and the trial only runs with at
# least MIN_TRAIN_VIEWS photos left to fit.
SCORE_VIEWS = 4
MIN_TRAIN_VIEWS = 8
# Under a time budget the trial takes at most this share of it, split evenly between the models. Each model first
# runs PROBE_STEPS, and where its share, at the pace of its last PROBE_STEPS - PROBE_WARMUP, would not take it past
# the trial's early prune (STEPS // 5), no model is scored: a grid not yet pruned is still clearing its air, and its
# renders of photos it did not fit rank the models by chance (the synthetic room, contracted against bounded +
# background: -0.36 to +0.71 dB in 23 trials that gave it under 60 steps, one of them a wrong pick whose fit lost 2 dB;
# +0.07 to +2.9 from 69 steps, but for one -0.08; bench/README.md, "The scene model by trial"). The proxies' pick
# stands and the share left goes to the fit.
BUDGET_SHARE = 0.2
PROBE_STEPS = 8
PROBE_WARMUP = 3
# A fit whose held-out PSNR falls this far below its train PSNR has learnt its photos but not the scene (floaters in
# new views, or an object lost from them). Sound fits of the shared captures stand well within it at every preset,
# while a fit that lost an object or was fitted on too few photos falls well past it (bench/README.md).
GAP_DB = 6.0


def model_name(model: SceneModel) -> str:
    """Which of MODELS a scene model is (a background model with NDC or a contraction counts as its frame)."""
    if model.fit_frame.ndc is not None:
        return "ndc"
    if model.fit_frame.contraction is not None:
        return "contracted"
    return "bounded + background" if model.background is not None else "bounded"


@dataclass
class Question:
    """A choice the proxies leave open: the models it is between and why."""
    models: tuple[str, ...]
    why: str


def forced_by(scene: dict, options) -> list[str]:
    """The settings that fix the model by hand (none: the fit may choose)."""
    forced = [f"fit.{name}={getattr(options, name)}" for name in ("ndc", "contract", "background")
              if getattr(options, name) != "auto"]
    if scene.get("overridden"):
        forced.append(f"normalize.scene_type={scene['type']}")
    return forced


def questions(scene: dict, options) -> list[Question]:
    """The choices normalize's measures leave open for this scene (empty: clear-cut, or a model set by hand)."""
    if forced_by(scene, options):
        return []
    measured, thresholds = scene.get("measured") or {}, scene.get("thresholds") or {}
    masked = bool(measured.get("masked")) or any(f.get("mask_path") for f in scene.get("frames", []))
    scene_type = scene.get("type")
    asked = []
    if measured.get("borderline") and isinstance(scene.get("forward"), dict) and scene_type != "forward":
        asked.append(Question(("ndc", inward_default(scene)),
                              f"viewing directions spread {measured['view_cone_deg']:.0f} deg, within "
                              f"normalize.borderline_deg of the forward limit {thresholds.get('forward_max_cone_deg', 30):g}"))
    beyond = measured.get("beyond_fraction")
    beyond_limit = float(thresholds.get("unbounded_min_beyond_fraction", 0.1))
    if scene_type == "unbounded" and not masked:
        if beyond is None:
            asked.append(Question(("contracted", "bounded + background"),
                                  "no sparse points to measure how far the surroundings reach"))
        elif CONTRACT_BAND[0] * beyond_limit <= beyond <= CONTRACT_BAND[1] * beyond_limit:
            asked.append(Question(("contracted", "bounded + background"),
                                  f"{beyond:.0%} of the sparse points lie beyond the foreground, within "
                                  f"{CONTRACT_BAND[0]:g}-{CONTRACT_BAND[1]:g}x the {beyond_limit:.0%} that makes "
                                  "a scene unbounded"))
    if scene_type in ("object", "unbounded") and not masked:
        near = []
        if beyond is not None and BACKDROP_BAND[0] * beyond_limit <= beyond <= BACKDROP_BAND[1] * beyond_limit:
            near.append(f"{beyond:.0%} of the sparse points beyond the foreground (threshold {beyond_limit:.0%})")
        empty = measured.get("empty_pixel_fraction")
        empty_limit = float(thresholds.get("object_min_empty_fraction", 0.2))
        if empty is not None and BACKDROP_BAND[0] * empty_limit <= empty <= BACKDROP_BAND[1] * empty_limit:
            near.append(f"{empty:.0%} of pixels an empty backdrop (threshold {empty_limit:.0%})")
        if near:
            asked.append(Question(("bounded", "bounded + background"), " and ".join(near)))
    return asked


def inward_default(scene: dict) -> str:
    """The model the fit's auto toggles give a scene of this type seen from around it."""
    if scene.get("type") == "unbounded":
        return "contracted" if reaches_far(scene) else "bounded + background"
    return "bounded"


def proxies_pick(scene: dict) -> str:
    """The model the fit's auto toggles give this scene: what normalize's proxies chose."""
    return "ndc" if scene.get("type") == "forward" else inward_default(scene)


@dataclass
class Tried:
    model: str
    held_out_psnr: float
    train_psnr: float
    seconds: float
    steps: int
    per_view: list[float] = field(default_factory=list)

    def record(self) -> dict:
        return {"model": self.model, "held_out_psnr": round(self.held_out_psnr, 3),
                "train_psnr": round(self.train_psnr, 3), "seconds": round(self.seconds, 1), "steps": self.steps,
                "per_view": [round(p, 3) for p in self.per_view]}


@dataclass
class Outcome:
    """What a trial found: the model to fit, why, and the record for fit.json."""
    model: str
    why: str
    record: dict

    def toggles(self) -> dict[str, str]:
        return dict(MODELS[self.model])


def score_views(count: int) -> list[int]:
    """Which of `count` training photos score the trial: SCORE_VIEWS evenly spread (none when too few remain)."""
    views = min(SCORE_VIEWS, count // 8)
    if views < 2 or count - views < MIN_TRAIN_VIEWS:
        return []
    step = count / views
    return sorted({int(step * (i + 0.5)) for i in range(views)})


def trial_options(options):
    """The fit's options for one short coarse level: its first resolution (no finer than MAX_RESOLUTION), pruned
    after a fifth of STEPS, no final prune."""
    first = min(Schedule.for_fit(options).resolutions[0], MAX_RESOLUTION)
    early = STEPS // 5
    return replace(options, resolutions=[first, first], steps=[early, STEPS - early], prune_final=False)


def run(scene: dict, options, train: RaySet, device: torch.device, asked: list[Question],
        seconds: float | None = None, say: Callable[[str], None] = lambda message: None) -> Outcome | None:
    """Fits each model the questions name on the trial's level and keeps the best (see the module's docstring); None
    where too few training photos are left to hold some out. `seconds`: the most the whole trial may take (each model
    gets its share and is scored where it stands when its share runs out); where a share is too short for a model to
    reach the level's early prune, the trial stops after its probe and the outcome keeps the proxies' pick with
    `skipped` saying why."""
    held = score_views(len(train))
    if not held:
        return None
    fitted = train.subset([i for i in range(len(train)) if i not in held])
    scored = train.subset(held)
    default = proxies_pick(scene)
    models = [default] + sorted({m for q in asked for m in q.models} - {default})
    base = trial_options(options)
    per_model = seconds / len(models) if seconds else None
    started = time.monotonic()
    runs = [_Run(scene, replace(base, **MODELS[name]), name, fitted, device) for name in models]
    record = {"questions": [{"models": list(q.models), "why": q.why} for q in asked], "proxies_pick": default}
    if per_model is not None:
        for trial in runs:
            trial.advance(PROBE_STEPS)
        short = [trial for trial in runs if trial.projected_steps(per_model) < base.steps[0]]
        if short:
            record["probed"] = [trial.probe_record(per_model) for trial in runs]
            record["seconds"] = round(time.monotonic() - started, 1)
            record["seconds_allowed"] = round(seconds, 1)
            record["skipped"] = (f"the budget's {seconds:.0f} s for a trial would take "
                                 + ", ".join(f"{t.name} about {t.projected_steps(per_model):.0f} steps" for t in short)
                                 + f", short of the early prune at step {base.steps[0]} before which scores rank "
                                 "the models by chance")
            say(f"model trial: kept {default}, normalize's pick: {record['skipped']}")
            return Outcome(default, record["skipped"], record)
    tried = []
    for trial in runs:
        tried.append(trial.finish(scored, per_model))
        say(f"model trial: {trial.name} {tried[-1].held_out_psnr:.2f} dB on {len(held)} training photos it did not "
            f"fit ({tried[-1].steps} steps at {base.resolutions[0]}^3, {tried[-1].seconds:.1f} s)")
    best = max(tried, key=lambda t: t.held_out_psnr)
    by_default = next(t for t in tried if t.model == default)
    if best.model != default and best.held_out_psnr >= by_default.held_out_psnr + MARGIN_DB:
        winner = best
        why = (f"{best.model} scored {best.held_out_psnr:.2f} dB against {by_default.held_out_psnr:.2f} dB for "
               f"{default}, normalize's pick, beating it by more than the {MARGIN_DB:g} dB margin")
    else:
        winner = by_default
        why = (f"{default}, normalize's pick, scored {by_default.held_out_psnr:.2f} dB and no other model beat it by "
               f"the {MARGIN_DB:g} dB margin (best other: " +
               ", ".join(f"{t.model} {t.held_out_psnr:.2f} dB" for t in tried if t is not by_default) + ")")
    record.update({"chosen": winner.model, "why": why, "margin_db": MARGIN_DB, "tried": [t.record() for t in tried],
                   "resolution": base.resolutions[0], "steps": base.total_steps, "fitted_photos": len(fitted),
                   "scored_photos": len(held), "seconds": round(time.monotonic() - started, 1),
                   "seconds_allowed": round(seconds, 1) if seconds else None})
    return Outcome(winner.model, why, record)


class _Run:
    """One model's trial fit: stepped a few steps at a time, its time kept, scored where it stands."""

    def __init__(self, scene: dict, options, name: str, fitted: RaySet, device: torch.device):
        started = time.monotonic()
        self.name, self.options = name, options
        model = SceneModel.create(scene, options, options.resolutions[0], focal_px=float(fitted.k[:, :2].median()),
                                  mean_colour=fitted.mean_colour())
        self.fitter = Fitter(model, options, fitted, device)
        self.step_seconds: list[float] = []
        self.seconds = time.monotonic() - started

    def advance(self, steps: int | None = None, seconds: float | None = None) -> None:
        """`steps` more steps (None: to the trial's last step), or fewer where its time passes `seconds` in all."""
        fitter = self.fitter
        end = min(self.options.total_steps, fitter.step + steps if steps is not None else self.options.total_steps)
        while fitter.step < end and (seconds is None or self.seconds <= seconds):
            begun = time.monotonic()
            if fitter.step == fitter.level_end(fitter.level):
                fitter.next_level()
            fitter.train_step()
            self.step_seconds.append(time.monotonic() - begun)
            self.seconds += self.step_seconds[-1]

    def projected_steps(self, seconds: float) -> float:
        """The steps `seconds` in all would give it, its time to here spent and the rest at its latest pace."""
        pace = float(np.mean(self.step_seconds[PROBE_WARMUP:] or self.step_seconds))
        return len(self.step_seconds) + max(0.0, seconds - self.seconds) / max(pace, 1e-9)

    def probe_record(self, seconds: float) -> dict:
        return {"model": self.name, "steps": len(self.step_seconds), "seconds": round(self.seconds, 2),
                "projected_steps": round(self.projected_steps(seconds))}

    def finish(self, scored: RaySet, seconds: float | None) -> Tried:
        """Its steps to the trial's last step or to `seconds` in all, then its PSNR on the photos it did not fit."""
        self.advance(seconds=seconds)
        begun = time.monotonic()
        per_view = []
        with torch.no_grad():
            for i in range(len(scored)):
                rgb = self.fitter.model.render_camera(scored.c2w[i].double().cpu().numpy(), scored.intrinsics[i],
                                                      backdrop=scored.backdrop(i))["rgb"]
                per_view.append(psnr(float(((rgb.cpu() - scored.image(i).cpu()) ** 2).mean())))
        self.seconds += time.monotonic() - begun
        tried = Tried(self.name, float(np.mean(per_view)), self.fitter.train_psnr(), self.seconds, self.fitter.step,
                      per_view)
        self.fitter = None  # its grid and optimiser freed before the next model's steps
        return tried


def summary(record: dict) -> str:
    """The summary line's words on a trial (its record): what was tried, the scores and the winner; or, where none
    was scored, which model the fit kept and why."""
    if not record.get("chosen"):
        return f"{record['proxies_pick']} model, normalize's pick, untried ({record['skipped']})"
    scores = ", ".join(f"{t['model']} {t['held_out_psnr']:.1f}" for t in record["tried"])
    by_default = next(t for t in record["tried"] if t["model"] == record["proxies_pick"])
    chosen = next(t for t in record["tried"] if t["model"] == record["chosen"])
    if chosen is by_default:
        verdict = f"kept normalize's pick, none beat it by {record['margin_db']:g} dB"
    else:
        verdict = f"+{chosen['held_out_psnr'] - by_default['held_out_psnr']:.1f} dB over normalize's {record['proxies_pick']}"
    return (f"{record['chosen']} model by trial ({scores} dB on {record['scored_photos']} photos it did not fit, "
            f"{record['seconds']:.0f} s: {verdict})")


def choose(scene: dict, options, train: RaySet, device: torch.device, budget_seconds: float, saved: Path,
           say: Callable[[str], None] = lambda message: None):
    """(the fit's options with the model chosen, the record for fit.json): a trial where normalize's measures leave
    the model open (kept in `saved`, so a resumed fit fits the model it started with), else the options as they are
    with why no trial ran."""
    if saved.is_file():
        record = json.loads(saved.read_text())
        return (replace(options, **MODELS[record["chosen"]]) if record.get("chosen") else options), record
    forced = forced_by(scene, options)
    asked = questions(scene, options)
    if forced:
        record = {"skipped": f"the model is set by hand ({', '.join(forced)})"}
    elif not asked:
        record = {"skipped": "normalize's measures are clear-cut"}
    else:
        say("model trial: " + "; ".join(f"{' or '.join(q.models)}? {q.why}" for q in asked))
        outcome = run(scene, options, train, device, asked, BUDGET_SHARE * budget_seconds if budget_seconds else None,
                      say)
        record = (outcome.record if outcome is not None else
                  {"questions": [{"models": list(q.models), "why": q.why} for q in asked], "proxies_pick": proxies_pick(scene),
                   "skipped": f"too few training photos ({len(train)}) to hold some out of a trial"})
    saved.write_text(json.dumps(record))
    return (replace(options, **MODELS[record["chosen"]]) if record.get("chosen") else options), record


def gap_advice(train_psnr: float, held_out_psnr: float | None, model: str, choice: dict, views_per_point) -> str:
    """The summary's words where held-out PSNR falls GAP_DB or more below train PSNR: what the gap means and what to
    try ('' otherwise)."""
    if held_out_psnr is None or train_psnr - held_out_psnr < GAP_DB:
        return ""
    others = [t["model"] for t in sorted(choice.get("tried", []), key=lambda t: -t["held_out_psnr"]) if t["model"] != model]
    others = others or [m for m in MODELS if m != model and (m != "ndc" or model == "ndc")]
    tries = [f"another model ({', '.join(_setting(m) for m in others[:2])})"]
    if views_per_point is not None and views_per_point < 16:
        tries.append(f"more photos ({views_per_point:.0f} views a point of the foreground)")
    else:
        tries.append("more photos from between the ones there are")
    tries.append("stronger TV (fit.tv_density, fit.tv_sh x10)")
    return (f"; held-out {held_out_psnr:.1f} dB is {train_psnr - held_out_psnr:.1f} dB below train {train_psnr:.1f} dB: "
            f"the {model} model learnt the photos, not the scene (floaters or a lost object in new views); try "
            + ", ".join(tries))


def _setting(model: str) -> str:
    """The settings that force `model` (those that matter beside the others' auto)."""
    return {"ndc": "fit.ndc=on", "contracted": "fit.contract=on", "bounded + background": "fit.contract=off fit.background=on",
            "bounded": "fit.ndc=off fit.contract=off fit.background=off"}[model]
