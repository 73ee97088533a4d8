"""The files a saved scene model is made of (SceneModel.save and load; the fit stage's output), free of torch so that
the pipeline's planning can name them without loading the model."""

MODEL_FILE = "model.json"   # the frame, options, background and grid header
GRID_FILE = "grid.pt"       # the grid's tensors
