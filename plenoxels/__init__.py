"""The Plenoxels model: sparse voxel grid, volume rendering, sparse RMSProp and TV, and what is built on it.

The layers, each importing only those below it: native.py loads the compiled core (plenoxels._C, built by
`make install` from csrc/); grid.py, optim.py, render.py and regularizers.py are the model; ndc.py, background.py,
fit_frame.py and scene_model.py make a fitted scene of it (options.py holds the options of a fit, free of torch);
train.py, mesh.py and surface.py are the machinery built on that, and a time budget's cost model (fit_cost.py), plan
(fit_plan.py) and pacer (budget.py) are built on train.py. reference.py is the core's PyTorch twin, for tests and
benchmarks only. Nothing here imports pipeline/ or stages/.
"""
