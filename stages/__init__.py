"""The stages, in the order they run: ingest, poses, normalize, fit, evaluate, export.

Each stage is a thin module here (its `run`); what the pipeline plans it by (settings, inputs, version) is in
settings/ (pipeline/stage.py says what each defines). Each stage's library is a wing below:
- capture/: the photos, videos and masks a user hands over, and synthetic captures (ingest)
- sfm/: structure from motion and pose files (poses)
- framing/: the scene's frame, type, box and visual hull (normalize)
- training/: the training photos as rays and the held-out split (fit; the model itself is plenoxels/)
- scoring/: metrics, LPIPS, camera paths, renders from chosen cameras (evaluate)
- interchange/: files for other tools: meshes, point clouds (export; the surface itself is plenoxels/surface/)
- common/: what every stage shares: JSON records, media files, frames as the fit sees them, stop requests.
Stages and their wings import plenoxels/ and each other's wings, never pipeline/.
"""
