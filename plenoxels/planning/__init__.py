"""How a fit spends its time: the cost model, the plan of levels for a budget, the schedule the fitter consults,
and the trial that chooses a scene's model."""
