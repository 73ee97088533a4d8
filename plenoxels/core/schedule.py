"""A fit's levels: which resolution each runs at and for how many steps (a `Schedule`, which the Fitter consults at
every step and a time budget re-plans), and how far the rates have decayed at a step."""
from __future__ import annotations

from dataclasses import dataclass

from plenoxels.core.options import TrainOptions


def coarse_start(resolutions: list[int] | tuple[int, ...], scale: float) -> list[int]:
    """`resolutions` with the first level, and the levels after it at the same resolution (its early-pruned rest),
    at `scale` of their resolution, rounded to a multiple of 8, never below min(32, that resolution) nor above it."""
    first = resolutions[0]
    coarse = first if scale >= 1 else min(first, max(min(32, first), 8 * round(first * scale / 8)))
    leading = next((level for level, r in enumerate(resolutions) if r != first), len(resolutions))
    return [coarse] * leading + list(resolutions[leading:])


@dataclass
class Schedule:
    """Which resolution each level of a fit runs at, and for how many steps. The Fitter consults it at every step; a
    time budget (plenoxels/planning/budget.py) owns the schedule of its fit and re-plans the levels not yet done."""
    resolutions: list[int]
    steps: list[int]
    converged_db: float = 0.0
    """The last level ends once it has converged (Fitter.end_if_converged); 0: it runs its steps. A time budget's
    schedule runs its plan: ending early would leave its time unused."""

    @classmethod
    def as_set(cls, options: TrainOptions) -> Schedule:
        """The options' levels as they are."""
        return cls(list(options.resolutions), list(options.steps))

    @classmethod
    def for_fit(cls, options: TrainOptions) -> Schedule:
        """The options' levels, the first at `first_level_scale` of its resolution (coarse_start), the last ending
        once it has converged where the options say so."""
        return cls(coarse_start(options.resolutions, options.first_level_scale), list(options.steps),
                   options.converged_db)

    @property
    def total_steps(self) -> int:
        return sum(self.steps)

    def level_end(self, level: int) -> int:
        """The step at which `level` ends."""
        return sum(self.steps[:level + 1])

    def rate_progress(self, step: int, level: int, per_level: bool) -> tuple[float, bool]:
        """How far the rates have decayed at `step` of `level` (0 at their start values, 1 at their final ones), and
        whether the density's ramp up applies: over the whole fit, or with `per_level` over each level after the first
        on its own, with no ramp (the first level keeps the whole fit's ramp and decay: it starts from nothing, its
        successors from a fitted grid)."""
        if not per_level or level == 0:
            return step / max(1, self.total_steps), True
        start = self.level_end(level - 1)
        return (step - start) / max(1, self.steps[level]), False
