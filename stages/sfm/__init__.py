"""Structure from motion and pose files: COLMAP through pycolmap, turned into the project's poses output.

- `options`: how SfM runs (`SfmOptions`, the poses stage's settings less where poses come from).
- `reconstruct`: feature extraction, matching and mapping (`reconstruct`).
- `exif`: focal length priors and camera grouping from the photos' EXIF.
- `model_checks`: images a model placed without support (`detached_images`) or against their matches
  (`contradicted_images`).
- `pose_files`: the pose files beside a scene's photos (`candidates`, `pose_files`).
- `pose_import`: poses the user already has (COLMAP model, transforms.json, LLFF, IDR/NeuS, and the formats below) as
  the same COLMAP model; `metashape`, `opensfm`, `nsvf` (NSVF's and NeRF++'s pose folders), `polycam`, `mvsnet` and
  `record3d` read their tools' files; `imported_model` the COLMAP model every import builds (its cameras, rigid
  poses, 360 views).
- `gimbal`: the world's up in an SfM model of a drone's photos, from their gimbal pitch (DJI's XMP).
- `outputs`: undistorting a model and writing transforms.json, images, masks, sparse/ and points.npz.
- `compare`: two pose sets of the same images compared up to a similarity.
"""
