"""LPIPS (stages/scoring/lpips.py): the PyTorch network against a plain numpy forward pass written apart from it
(flax's channels-last layout, float64), the numpy-only weights loader, and the error when the weights
are missing."""
from __future__ import annotations

import os
import pickle

import numpy as np
import pytest

from stages.scoring import lpips
from plenoxels.core.errors import UserError
from prerequisites import missing


@pytest.fixture(scope="module")
def weights_path():
    path = lpips.default_weights_path()
    if not path.is_file():
        missing(f"LPIPS weights not installed at {path}: run `make install` (or python -m stages.scoring.lpips install)")
    return path


# ------------------------------------------------------------------------------------------------
# Independent reference: images [h, w, 3], kernels [kh, kw, in, out] as stored, float64.


def _conv(x: np.ndarray, kernel: np.ndarray, bias: np.ndarray, stride: int, pad: int) -> np.ndarray:
    x = np.pad(x, ((pad, pad), (pad, pad), (0, 0)))
    kh, kw = kernel.shape[:2]
    oh, ow = (x.shape[0] - kh) // stride + 1, (x.shape[1] - kw) // stride + 1
    out = np.zeros((oh, ow, kernel.shape[3]))
    for dy in range(kh):
        for dx in range(kw):
            patch = x[dy:dy + stride * (oh - 1) + 1:stride, dx:dx + stride * (ow - 1) + 1:stride]
            out += patch @ kernel[dy, dx]
    return out + bias


def _max_pool(x: np.ndarray) -> np.ndarray:
    oh, ow = (x.shape[0] - 3) // 2 + 1, (x.shape[1] - 3) // 2 + 1
    windows = [x[dy:dy + 2 * (oh - 1) + 1:2, dx:dx + 2 * (ow - 1) + 1:2] for dy in range(3) for dx in range(3)]
    return np.max(windows, axis=0)


def numpy_lpips(a: np.ndarray, b: np.ndarray, tree: dict) -> float:
    """LPIPS v0.1 (AlexNet) of two [h, w, 3] images in [0, 1]."""
    net = {k: {n: v.astype(np.float64) for n, v in layer.items()} for k, layer in tree["AlexNet_0"].items()}
    shift, scale = np.array([-0.030, -0.088, -0.188]), np.array([0.458, 0.448, 0.450])

    def features(img):
        x = ((img.astype(np.float64) * 2 - 1) - shift) / scale
        x = np.maximum(_conv(x, net["Conv_0"]["kernel"], net["Conv_0"]["bias"], 4, 2), 0)
        feats = [x]
        x = np.maximum(_conv(_max_pool(x), net["Conv_1"]["kernel"], net["Conv_1"]["bias"], 1, 2), 0)
        feats.append(x)
        x = np.maximum(_conv(_max_pool(x), net["Conv_2"]["kernel"], net["Conv_2"]["bias"], 1, 1), 0)
        feats.append(x)
        for name in ("Conv_3", "Conv_4"):
            x = np.maximum(_conv(x, net[name]["kernel"], net[name]["bias"], 1, 1), 0)
            feats.append(x)
        return feats

    total = 0.0
    for i, (fa, fb) in enumerate(zip(features(a), features(b))):
        na = fa / (np.sqrt((fa ** 2).sum(axis=-1, keepdims=True)) + 1e-10)
        nb = fb / (np.sqrt((fb ** 2).sum(axis=-1, keepdims=True)) + 1e-10)
        head = tree[f"NetLinLayer_{i}"]["Conv_0"]["kernel"][0, 0, :, 0].astype(np.float64)
        total += float((((na - nb) ** 2) @ head).mean())
    return total


def _test_images(h: int = 80, w: int = 96) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A structured image (gradients, a disc, stripes), a noisy copy and a shifted copy."""
    rng = np.random.default_rng(0)
    y, x = np.mgrid[0:h, 0:w] / np.array([h, w])[:, None, None]
    image = np.stack([x, y, 0.5 + 0.5 * np.sin(12 * x)], axis=-1)
    image[(x - 0.6) ** 2 + (y - 0.4) ** 2 < 0.05] = (0.9, 0.2, 0.1)
    image[:, ::7] *= 0.5
    noisy = np.clip(image + rng.normal(0, 0.08, image.shape), 0, 1)
    shifted = np.roll(image, 3, axis=1)
    return image.astype(np.float32), noisy.astype(np.float32), shifted.astype(np.float32)


# ------------------------------------------------------------------------------------------------


def test_lpips_of_an_image_with_itself_is_zero(weights_path):
    image, noisy, _ = _test_images()
    assert lpips.image_lpips(image, image, weights_path) == 0.0
    assert lpips.image_lpips(noisy, noisy, weights_path) == 0.0


def test_lpips_matches_an_independent_numpy_forward_pass(weights_path):
    image, noisy, shifted = _test_images()
    tree = lpips.load_numpy_pickle(weights_path)
    for other in (noisy, shifted):
        expected = numpy_lpips(image, other, tree)
        got = lpips.image_lpips(image, other, weights_path)
        assert expected > 0.01
        assert got == pytest.approx(expected, abs=1e-5)
    # Symmetric, and uint8 input means the same picture.
    assert lpips.image_lpips(noisy, image, weights_path) == pytest.approx(lpips.image_lpips(image, noisy, weights_path), abs=1e-6)
    as_bytes = (image * 255 + 0.5).astype(np.uint8)
    assert lpips.image_lpips(as_bytes, noisy, weights_path) == pytest.approx(
        lpips.image_lpips(as_bytes.astype(np.float32) / 255, noisy, weights_path), abs=1e-7)


def test_more_noise_is_farther(weights_path):
    image, _, _ = _test_images()
    rng = np.random.default_rng(1)
    scores = [lpips.image_lpips(image, np.clip(image + rng.normal(0, s, image.shape), 0, 1).astype(np.float32), weights_path)
              for s in (0.02, 0.1, 0.3)]
    assert scores[0] < scores[1] < scores[2]


class _RunsCode:
    def __reduce__(self):
        return (os.getcwd, ())


def test_weights_loader_accepts_only_numpy_arrays(tmp_path):
    good = tmp_path / "good.ckpt"
    good.write_bytes(pickle.dumps({"layer": {"kernel": np.arange(6, dtype=np.float32).reshape(2, 3)}}))
    assert np.array_equal(lpips.load_numpy_pickle(good)["layer"]["kernel"], np.arange(6).reshape(2, 3))

    code = tmp_path / "code.ckpt"
    code.write_bytes(pickle.dumps({"layer": _RunsCode()}))
    with pytest.raises(pickle.UnpicklingError, match="posix.getcwd|os.getcwd|nt.getcwd"):
        lpips.load_numpy_pickle(code)
    objects = tmp_path / "objects.ckpt"
    objects.write_bytes(pickle.dumps({"layer": np.array([1, "x"], dtype=object)}))
    with pytest.raises(pickle.UnpicklingError, match="numeric numpy array"):
        lpips.load_numpy_pickle(objects)
    other = tmp_path / "other.ckpt"
    other.write_bytes(pickle.dumps({"layer": {1, 2}}))
    with pytest.raises(pickle.UnpicklingError):
        lpips.load_numpy_pickle(other)


def test_images_too_small_for_alexnet_are_refused(weights_path):
    image = _test_images(h=lpips.MIN_SIDE - 1, w=64)[0]
    with pytest.raises(ValueError, match="at least"):
        lpips.image_lpips(image, image, weights_path)
    image = _test_images(h=lpips.MIN_SIDE, w=lpips.MIN_SIDE)[0]
    assert lpips.image_lpips(image, image, weights_path) == 0.0


def test_missing_weights_is_a_one_line_error_naming_make_install(tmp_path):
    with pytest.raises(UserError) as info:
        lpips.read_weights(tmp_path / "absent.ckpt")
    assert "make install" in str(info.value) and "\n" not in str(info.value)
