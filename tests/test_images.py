"""Frame images as the fit and evaluate stages load them."""
import math

import imageio.v3 as iio
import numpy as np

from pipeline.images import load_frame


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
