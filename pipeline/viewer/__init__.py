"""A web viewer of a scene's output folder (`python -m pipeline view OUT`, `make view`), built on viser.

It shows, in the normalised world (z up, foreground in the unit cube), what the stages have written:
the training and held-out cameras with their photos, the sparse points, the exported mesh and point
cloud, the foreground box, and the radiance field rendered by our own renderer for each browser's camera
(a low-resolution preview while the camera moves, refined once it stops; RGB, depth or opacity). Beside a
running fit it swaps in each new checkpoint. A crop box set in it is saved to OUT/view/crop.json and
handed to the export stage as `export.crop`.

It listens on 127.0.0.1 unless told otherwise and never opens viser's public share tunnel.

- content.py: reading the output folder; model_source.py: the newest model (fit or checkpoint);
  rendering.py: browser camera -> our camera, renders on a worker thread; crop.py: the crop file;
  server.py: the viser scene, controls and the checkpoint watcher.
"""
from pipeline.viewer.server import Viewer, ViewOptions

__all__ = ["Viewer", "ViewOptions"]
