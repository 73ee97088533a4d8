"""How normalize frames a scene and decides its type: the options the normalize stage's settings are, free of the
camera model's torch, so a settings listing and the pipeline's cache keys read them without loading it. `check`
raises a one-line UserError for a bad value, naming the key as `section.name`."""
from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

from plenoxels.core.errors import require


@dataclass
class SceneOptions:
    """How the scene is framed and typed (the normalize stage's settings)."""
    scene_type: Literal["auto", "object", "forward", "unbounded"] = "auto"
    """Scene type the fit models; auto: decided from the cameras, points and backdrop."""
    holdout_every: int = 8
    """Every Nth image by sorted name is held out for evaluation; 0: none. A dataset that names its splits
    (train/, val/, test/ folders; NSVF's 0_, 1_, 2_ names) holds out the split ingest.holdout_split names instead."""
    train_every: int = 1
    """Train on every Nth of the training photos by sorted name and leave the rest unused (1: all): a few-views
    study, as the papers' 25 of lego's 100 training views."""
    margin: float = 0.1
    """Space around the foreground: its largest half-size maps to 1/(1+margin), in [0, 1]."""
    forward_max_cone_deg: float = 30.0
    """Forward when 90% of viewing directions lie within this many degrees of their mean."""
    borderline_deg: float = 8.0
    """Spreads within this many degrees of forward_max_cone_deg are borderline: typed for the inward model (grid and
    background), which degrades gracefully where NDC's single frustum cannot hold the views, and the fit tries NDC
    against it on a short coarse level (plenoxels/planning/model_trial.py); the summary says so."""
    beyond_factor: float = 2.0
    """A point is beyond the foreground outside [-f, f]^3 in the normalised frame (f > 1)."""
    unbounded_min_beyond_fraction: float = 0.1
    """Unbounded when at least this share of the sparse points lies beyond the foreground."""
    object_min_empty_fraction: float = 0.2
    """Object needs at least this share of sampled pixels to show an empty backdrop."""
    silhouette_box: bool = True
    """Box the foreground by the visual hull of the training photos' silhouettes where they carry masks (or alpha) or
    stand on a flat backdrop, so thin parts the sparse points miss stay inside; off: the box of the points' bulk."""
    masked_backdrop: Literal["fit", "own"] = "own"
    """What a masked photo's pixels outside its mask are trained as: empty space on the photo's own colour there, the
    median outside its mask (own: a mask drawn a pixel or two loose then holds backdrop that matches what lies past
    it; a held-out view takes its nearest training cameras'), or on fit.background_color (fit; always for photos
    cut out by their own alpha, where nothing outside the mask is a backdrop)."""

    def check(self, section: str = "normalize") -> None:
        require(self.holdout_every == 0 or self.holdout_every >= 2,
                f"{section}.holdout_every must be 0 (hold none out) or at least 2")
        require(self.train_every >= 1, f"{section}.train_every must be at least 1 (1: every training photo)")
        require(0.0 <= self.margin <= 1.0, f"{section}.margin must be in [0, 1]")
        require(0.0 < self.forward_max_cone_deg < 90.0, f"{section}.forward_max_cone_deg must be in (0, 90)")
        require(0.0 <= self.borderline_deg < self.forward_max_cone_deg,
                f"{section}.borderline_deg must be >= 0 and below {section}.forward_max_cone_deg")
        require(self.beyond_factor > 1.0, f"{section}.beyond_factor must be greater than 1")
        require(0.0 < self.unbounded_min_beyond_fraction < 1.0,
                f"{section}.unbounded_min_beyond_fraction must be in (0, 1)")
        require(0.0 < self.object_min_empty_fraction < 1.0, f"{section}.object_min_empty_fraction must be in (0, 1)")
