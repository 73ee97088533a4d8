"""A 360 frame's views straight down and straight up, posed from its views around the horizon that SfM posed. A
frame's views share its centre and differ by their turn alone (panorama.view_rotation), so each posed view turned back
by its own turn gives the frame's camera-to-world: their rotations averaged (the nearest rotation to their mean),
their centres too, and turned again to the pole. SfM does not pose the pole views itself: a ceiling's or the sky's
plain view finds few matches, and the view down shows whatever holds the camera, which moves with it."""
from __future__ import annotations

from collections import defaultdict

import numpy as np
import pycolmap

from stages.capture.panorama import at_pole, view_rotation
from stages.sfm.imported_model import add_image
from plenoxels.core.cameras import opengl_c2w_from_colmap_w2c


def frame_poses(reconstruction: pycolmap.Reconstruction, records: list[dict]) -> dict[str, tuple[np.ndarray, int]]:
    """Each 360 frame's camera-to-world (OpenGL axes) from its posed views, and one of those views' camera ids."""
    images = {image.name: image for image in reconstruction.images.values() if image.has_pose}
    turned_back: dict[str, list[np.ndarray]] = defaultdict(list)
    camera_of: dict[str, int] = {}
    for record in records:
        image = images.get(f"{record['name']}.png")
        if image is None or "panorama" not in record or at_pole(record):
            continue
        w2c = image.cam_from_world()
        c2w = opengl_c2w_from_colmap_w2c(w2c.rotation.matrix(), w2c.translation)
        c2w[:3, :3] = c2w[:3, :3] @ view_rotation(record["panorama"]["yaw"]).T
        turned_back[record["panorama"]["frame"]].append(c2w)
        camera_of[record["panorama"]["frame"]] = image.camera_id
    poses = {}
    for frame, c2ws in turned_back.items():
        u, _, vt = np.linalg.svd(np.mean([view[:3, :3] for view in c2ws], axis=0))
        averaged = np.eye(4)
        averaged[:3, :3] = u @ np.diag([1.0, 1.0, np.linalg.det(u @ vt)]) @ vt
        averaged[:3, 3] = np.mean([view[:3, 3] for view in c2ws], axis=0)
        poses[frame] = (averaged, camera_of[frame])
    return poses


def add_pole_views(reconstruction: pycolmap.Reconstruction, records: list[dict]) -> list[str]:
    """Adds each pole view whose frame has a posed view to the model, at its frame's pose turned to the pole; returns
    the names of those whose frame has none."""
    poses = frame_poses(reconstruction, records)
    unposed = []
    next_id = max(reconstruction.images, default=0) + 1
    for record in filter(at_pole, records):
        if record["panorama"]["frame"] not in poses:
            unposed.append(record["name"])
            continue
        c2w, camera_id = poses[record["panorama"]["frame"]]
        add_image(reconstruction, next_id, record, camera_id, c2w, f"the 360 frame {record['panorama']['frame']}",
                  view_rotation(record["panorama"]["yaw"], record["panorama"]["pitch"]))
        next_id += 1
    return unposed
