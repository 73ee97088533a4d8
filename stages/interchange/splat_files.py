"""The export's splat files, as splat viewers and engines open them, and their readers.

splats.ply: the layout of the original 3D Gaussian Splatting code, which most splat tools read (SuperSplat, the
antimatter15 and gsplat.js web viewers, the Blender and Unity add-ons, nerfstudio, Polycam): one binary little-endian
`vertex` element of float32 properties x, y, z, nx, ny, nz (zeros), f_dc_0..2 (the SH degree-0 term of R, G, B),
f_rest_0.. (the higher SH terms, all of R's, then G's, then B's), opacity (a logit), scale_0..2 (logs of the standard
deviations), rot_0..3 (a quaternion, w first, as the splats hold it: readers normalise it). Written in the frame's own axes, as the mesh PLY.

splats.glb: glTF 2.0 with KHR_gaussian_splatting (three.js, Babylon.js, CesiumJS, PlayCanvas): one POINTS primitive
whose attributes are POSITION, KHR_gaussian_splatting:ROTATION (unit quaternion, x, y, z, w), :SCALE (linear standard
deviations), :OPACITY (in [0, 1]) and :SH_DEGREE_l_COEF_n (RGB per coefficient, n from the lowest order m up), with
COLOR_0 (the degree-0 colour in linear light, the opacity as alpha) for viewers without the extension, which draw the
splats as a coloured point cloud. The kernel is `ellipse`, the colour space `srgb_rec709_display` (the photos' own).
Like the mesh's GLB, y-up: written in GLTF_FROM_ZUP's axes, the SH turned with them (plenoxels/splats/model.py).
"""
from __future__ import annotations

import json
import struct
from pathlib import Path

import numpy as np
import torch
from plyfile import PlyData, PlyElement

from stages.common.media import GLTF_FROM_ZUP
from plenoxels.splats.model import Splats, sh_degree_of

EXTENSION = "KHR_gaussian_splatting"
FLOAT, ARRAY_BUFFER, POINTS = 5126, 34962, 0
GLB_MAGIC, JSON_CHUNK, BIN_CHUNK = 0x46546C67, 0x4E4F534A, 0x004E4942


def ply_properties(sh_degree: int) -> list[str]:
    """The vertex properties of a splat PLY, in order."""
    rest = 3 * ((sh_degree + 1) ** 2 - 1)
    return (["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"] + [f"f_rest_{i}" for i in range(rest)]
            + ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"])


def write_splat_ply(path: Path, splats: Splats) -> None:
    n, names = splats.count, ply_properties(splats.sh_degree)
    columns = torch.cat([splats.means, torch.zeros(n, 3), splats.sh[:, :, 0], splats.sh[:, :, 1:].reshape(n, -1),
                         splats.opacity_logits[:, None], splats.log_scales, splats.quats], dim=1).detach().float().numpy()
    table = np.empty(n, dtype=[(name, "<f4") for name in names])
    for i, name in enumerate(names):
        table[name] = columns[:, i]
    PlyData([PlyElement.describe(table, "vertex")], byte_order="<").write(str(path))


def read_splat_ply(path: Path) -> Splats:
    vertex = PlyData.read(str(path))["vertex"]
    names = [p.name for p in vertex.properties]
    rest = sum(name.startswith("f_rest_") for name in names)
    degree = sh_degree_of(rest // 3 + 1)
    if names != ply_properties(degree):
        raise ValueError(f"{path} is not a splat PLY in the 3D Gaussian Splatting layout")
    col = lambda *keys: torch.as_tensor(np.stack([np.asarray(vertex[k], dtype=np.float32) for k in keys], 1))  # noqa: E731
    n = len(vertex.data)
    sh = col("f_dc_0", "f_dc_1", "f_dc_2")[:, :, None]
    if rest:
        sh = torch.cat([sh, col(*[f"f_rest_{i}" for i in range(rest)]).reshape(n, 3, rest // 3)], dim=2)
    return Splats(col("x", "y", "z"), col("scale_0", "scale_1", "scale_2"), col("rot_0", "rot_1", "rot_2", "rot_3"),
                  col("opacity")[:, 0], sh)


def srgb_to_linear(c: np.ndarray) -> np.ndarray:
    return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)


def gltf_attributes(splats: Splats) -> dict[str, np.ndarray]:
    """Attribute semantic -> float32 values [N, width] of a splat primitive, in glTF's order."""
    s = splats.detached()
    opacity = s.opacities()[:, None]
    diffuse = s.diffuse().numpy()
    quats = s.quats / s.quats.norm(dim=1, keepdim=True).clamp_min(1e-12)
    out = {"POSITION": s.means, "COLOR_0": np.concatenate([srgb_to_linear(diffuse), opacity.numpy()], axis=1),
           f"{EXTENSION}:ROTATION": quats[:, [1, 2, 3, 0]], f"{EXTENSION}:SCALE": torch.exp(s.log_scales),
           f"{EXTENSION}:OPACITY": opacity}
    for l in range(s.sh_degree + 1):
        for n in range(2 * l + 1):
            out[f"{EXTENSION}:SH_DEGREE_{l}_COEF_{n}"] = s.sh[:, :, l * l + n]
    return {k: np.ascontiguousarray(np.asarray(v, dtype=np.float32)) for k, v in out.items()}


def write_splat_glb(path: Path, splats: Splats) -> None:
    """The splats (in the frame's own axes) as a binary glTF, y-up."""
    attributes = gltf_attributes(splats.transformed(GLTF_FROM_ZUP))
    kinds = {1: "SCALAR", 3: "VEC3", 4: "VEC4"}
    blob, views, accessors = bytearray(), [], []
    for values in attributes.values():
        accessor = {"bufferView": len(views), "componentType": FLOAT, "count": len(values),
                    "type": kinds[values.shape[1]]}
        if len(accessors) == 0 and len(values):  # POSITION: glTF requires its bounds
            accessor.update(min=values.min(0).tolist(), max=values.max(0).tolist())
        views.append({"buffer": 0, "byteOffset": len(blob), "byteLength": values.nbytes, "target": ARRAY_BUFFER})
        accessors.append(accessor)
        blob += values.tobytes()
    document = {
        "asset": {"version": "2.0", "generator": "voxfield"},
        "extensionsUsed": [EXTENSION],
        "scene": 0, "scenes": [{"nodes": [0]}], "nodes": [{"mesh": 0, "name": "splats"}],
        "meshes": [{"name": "splats", "primitives": [{
            "attributes": {name: i for i, name in enumerate(attributes)}, "mode": POINTS,
            "extensions": {EXTENSION: {"kernel": "ellipse", "colorSpace": "srgb_rec709_display",
                                       "projection": "perspective", "sortingMethod": "cameraDistance"}}}]}],
        "accessors": accessors, "bufferViews": views, "buffers": [{"byteLength": len(blob)}],
    }
    text = json.dumps(document, separators=(",", ":")).encode()
    text += b" " * (-len(text) % 4)
    blob += b"\0" * (-len(blob) % 4)
    with open(path, "wb") as f:
        f.write(struct.pack("<III", GLB_MAGIC, 2, 12 + 8 + len(text) + 8 + len(blob)))
        f.write(struct.pack("<II", len(text), JSON_CHUNK) + text)
        f.write(struct.pack("<II", len(blob), BIN_CHUNK) + bytes(blob))


def read_glb(path: Path) -> tuple[dict, dict[str, np.ndarray]]:
    """A GLB's JSON and, per attribute of its first primitive, the values [N, width] its accessor reads."""
    data = Path(path).read_bytes()
    magic, version, length = struct.unpack_from("<III", data, 0)
    if magic != GLB_MAGIC or version != 2 or length != len(data):
        raise ValueError(f"{path} is not a glTF 2.0 binary")
    json_length, kind = struct.unpack_from("<II", data, 12)
    document = json.loads(data[20:20 + json_length])
    bin_length, bin_kind = struct.unpack_from("<II", data, 20 + json_length)
    if kind != JSON_CHUNK or bin_kind != BIN_CHUNK:
        raise ValueError(f"{path}: chunks are not JSON then BIN")
    blob = data[28 + json_length:28 + json_length + bin_length]
    widths = {"SCALAR": 1, "VEC3": 3, "VEC4": 4}
    values = {}
    for name, index in document["meshes"][0]["primitives"][0]["attributes"].items():
        accessor = document["accessors"][index]
        view = document["bufferViews"][accessor["bufferView"]]
        width = widths[accessor["type"]]
        values[name] = np.frombuffer(blob, dtype="<f4", count=accessor["count"] * width,
                                     offset=view["byteOffset"] + accessor.get("byteOffset", 0)).reshape(-1, width)
    return document, values


def read_splat_glb(path: Path) -> Splats:
    """The splats of a GLB written by write_splat_glb, back in the frame's own axes."""
    _, values = read_glb(path)
    ext = lambda name: torch.as_tensor(values[f"{EXTENSION}:{name}"].copy())  # noqa: E731
    degree = max(int(name.rsplit(":", 1)[1].split("_")[2]) for name in values if ":SH_DEGREE_" in name)
    sh = torch.stack([ext(f"SH_DEGREE_{l}_COEF_{n}") for l in range(degree + 1) for n in range(2 * l + 1)], dim=2)
    opacity = ext("OPACITY")[:, 0].double().clamp(1e-7, 1 - 1e-7)
    splats = Splats(torch.as_tensor(values["POSITION"].copy()), torch.log(ext("SCALE")), ext("ROTATION")[:, [3, 0, 1, 2]],
                    (torch.log(opacity) - torch.log1p(-opacity)).float(), sh)
    return splats.transformed(np.linalg.inv(GLTF_FROM_ZUP))
