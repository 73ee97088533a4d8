"""Frame images as the fit and evaluate stages load them."""
import math

import imageio.v3 as iio
import numpy as np
import pytest

from stages.common.frames import load_frame, load_frames, read_frame
from plenoxels.core.errors import UserError


def test_masked_images_are_composited_onto_the_background(tmp_path):
    rgb = np.zeros((4, 6, 3), dtype=np.uint8)
    rgb[..., 0] = 200
    alpha = np.zeros((4, 6), dtype=np.uint8)
    alpha[:, :3] = 255
    alpha[:, 3] = 128
    iio.imwrite(tmp_path / "a.png", np.concatenate([rgb, alpha[..., None]], axis=-1))
    frame = {"file_path": "a.png", "mask_path": "a.png", "fl_x": 5.0, "fl_y": 5.0, "cx": 3.0, "cy": 2.0, "w": 6, "h": 4}
    image, k = load_frame(tmp_path, frame, 1.0, (0.0, 1.0, 0.0))
    a = alpha.astype(np.float32) / 255
    expected = np.stack([200 / 255 * a, 1 - a, np.zeros_like(a)], axis=-1)
    np.testing.assert_allclose(image, expected, atol=1e-6)
    half, k_half = load_frame(tmp_path, frame, 0.5, (1.0, 1.0, 1.0))
    assert half.shape == (2, 3, 3) and (k_half.w, k_half.h) == (3, 2) and math.isclose(k_half.fl_x, 2.5)


def test_a_photo_that_is_its_own_mask_loads_as_a_separate_mask_does(tmp_path):
    rng = np.random.default_rng(0)
    rgba = rng.integers(0, 256, (8, 10, 4), dtype=np.uint8)
    iio.imwrite(tmp_path / "photo.png", rgba)
    iio.imwrite(tmp_path / "colour.png", rgba[..., :3])
    iio.imwrite(tmp_path / "mask.png", rgba[..., 3])
    camera = {"fl_x": 9.0, "fl_y": 9.0, "cx": 5.0, "cy": 4.0, "w": 10, "h": 8}
    together, _, mask = read_frame(tmp_path, {"file_path": "photo.png", "mask_path": "photo.png", **camera}, 0.5,
                                   (0.2, 0.4, 0.6))
    apart, _, mask_apart = read_frame(tmp_path, {"file_path": "colour.png", "mask_path": "mask.png", **camera}, 0.5,
                                      (0.2, 0.4, 0.6))
    np.testing.assert_array_equal(together, apart)
    # The mask it composited with, at the image's size: each pixel the mean of the 2x2 it covers.
    expected = rgba[..., 3].astype(np.float32).reshape(4, 2, 5, 2).mean(axis=(1, 3)) / 255
    np.testing.assert_allclose(mask, expected, atol=1e-6)
    np.testing.assert_array_equal(mask, mask_apart)


def test_frames_load_on_threads_in_order_as_one_by_one(tmp_path):
    rng = np.random.default_rng(1)
    frames = []
    for i, (w, h) in enumerate([(12, 8), (9, 7), (16, 10), (12, 8), (5, 4)]):
        iio.imwrite(tmp_path / f"{i}.png", rng.integers(0, 256, (h, w, 3), dtype=np.uint8))
        frames.append({"file_path": f"{i}.png", "fl_x": 8.0, "fl_y": 8.0, "cx": w / 2, "cy": h / 2, "w": w, "h": h})
    one_by_one = [load_frame(tmp_path, f, 0.5, (1.0, 1.0, 1.0)) for f in frames]
    threaded = list(load_frames(tmp_path, frames, 0.5, (1.0, 1.0, 1.0), threads=3))
    assert len(threaded) == len(frames)
    for (image, k, mask), (expected, k_expected) in zip(threaded, one_by_one):
        assert mask is None
        np.testing.assert_array_equal(image, expected)
        assert (k.w, k.h, k.fl_x) == (k_expected.w, k_expected.h, k_expected.fl_x)


def test_a_missing_frame_stops_the_threaded_load_with_the_one_line_error(tmp_path):
    iio.imwrite(tmp_path / "a.png", np.zeros((4, 4, 3), dtype=np.uint8))
    camera = {"fl_x": 4.0, "fl_y": 4.0, "cx": 2.0, "cy": 2.0, "w": 4, "h": 4}
    frames = [{"file_path": "a.png", **camera}, {"file_path": "gone.png", **camera}]
    with pytest.raises(UserError, match="gone.png listed in scene.json is missing"):
        list(load_frames(tmp_path, frames, 1.0, (1.0, 1.0, 1.0), threads=2))
