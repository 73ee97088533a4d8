"""The Plenoxels model (sparse voxel grid, volume rendering, sparse RMSProp and TV) and what is built on it.

Three wings, each importing only itself and those listed before it:
- `core/`: the model. native.py loads the compiled core (plenoxels._C, built by `make install` from csrc/);
  grid.py, optim.py, render.py and regularizers.py are the model; ndc.py, background.py, fit_frame.py and
  scene_model.py make a fitted scene of it; options.py holds a fit's options; train.py fits it, drawing its batches
  from ray_set.py, with what it measures of its photos (error_map.py, photo_colour.py). reference.py is the core's
  PyTorch twin, for tests and benchmarks only.
- `planning/`: how a fit spends its time: the cost model (fit_cost.py), the plan of levels (fit_plan.py), the time
  budget's schedule (budget.py) and the trial that chooses the scene model (model_trial.py).
- `surface/`: the fitted field as a surface: views.py (where training rays end), mesh.py (marching cubes, sealing,
  cleaning), ground.py, view_alignment.py and texture.py.
Nothing here imports pipeline/ or stages/.
"""
