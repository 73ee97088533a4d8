"""A/B runs of budgeted fits that plan alike: with BENCH_RETIME set (a factor, e.g. 1.3), every cached calibration is
scaled by that factor instead of by its retime, whose reading moves 0.85-1.31 from one run to the next on a shared
machine and with it the first plan. Python loads this file at start-up from PYTHONPATH, so the bench's child
processes (one per run) get it too:

    BENCH_RETIME=1.3 PYTHONPATH=bench/retime python -m bench.real_scenes --scenes synthetic_room --budgets 1m ...

run from the checkout whose code it measures. A fit's record says the factor (`slower_now`) and what the retime read
(`retimed_as_measured`)."""
import os
import sys

_factor = os.environ.get("BENCH_RETIME")
if _factor:
    sys.path.insert(0, os.getcwd())
    from plenoxels.planning import budget, fit_cost

    _measured = fit_cost.calibrate

    def _calibrate(*args, **kwargs):
        costs, record = _measured(*args, **kwargs)
        if record.get("cached"):
            costs = fit_cost.CostModel(**record["costs"]).scaled(float(_factor))
            record = {**record, "slower_now": float(_factor), "retimed_as_measured": record.get("slower_now")}
        return costs, record

    fit_cost.calibrate = _calibrate
    budget.calibrate = _calibrate
