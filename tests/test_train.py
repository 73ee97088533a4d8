"""The training loop's parts: batches of real pixels and the learning-rate schedule."""
import math

import numpy as np
import pytest
import torch

from pipeline.images import load_frame
from pipeline.io import read_json
from plenoxels.cameras import rays_from_camera
from plenoxels.train import RaySet, decayed_lr
from test_fit import make_scene


def test_batches_are_the_rays_and_colours_of_real_pixels(tmp_path):
    root = make_scene(tmp_path)
    frames = [f for f in read_json(root / "normalize" / "scene.json")["frames"] if f["split"] == "train"]
    loaded = [load_frame(root, frame, 1.0, (1.0, 1.0, 1.0)) for frame in frames]
    train = RaySet([image for image, _ in loaded], [np.asarray(f["transform_matrix"]) for f in frames],
                   [k for _, k in loaded])
    generator = torch.Generator().manual_seed(3)
    for mode in ("tiles", "rays"):
        o, d, colour = train.batch(1024, mode, 16, generator)
        # Every ray of the batch is the ray of some pixel whose colour is the target.
        c2w = train.c2w[0].double().numpy()
        all_o, all_d = rays_from_camera(c2w, train.intrinsics[0])
        first = (o - train.c2w[0, :3, 3]).norm(dim=1) < 1e-6
        assert first.any()
        match = torch.cdist(d[first].double(), all_d.reshape(-1, 3).double()).min(dim=1)
        assert float(match.values.max()) < 1e-5
        pixels = train.pixels[: train.offsets[1]].float() / 255
        np.testing.assert_allclose(colour[first].numpy(), pixels[match.indices].numpy(), atol=1e-6)
    o, d, _ = train.batch(16 * 16, "tiles", 16, generator)
    # One tile: one camera, neighbouring pixels.
    assert (o == o[0]).all()


def test_learning_rate_schedule():
    assert math.isclose(decayed_lr(30.0, 0.05, 0.0), 30.0)  # svox2's density rates, as plain numbers
    assert math.isclose(decayed_lr(30.0, 0.05, 1.0), 0.05)
    assert math.isclose(decayed_lr(30.0, 0.05, 0.5), math.sqrt(30.0 * 0.05))
    assert decayed_lr(30.0, 0.05, 0.0, delay=0.2) == pytest.approx(0.3)
    assert decayed_lr(30.0, 0.05, 0.2, delay=0.2) == pytest.approx(decayed_lr(30.0, 0.05, 0.2))
