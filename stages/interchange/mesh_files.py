"""The export's mesh files, as DCC tools open them: PLY with vertex colours, and OBJ (+ MTL + PNG) and glTF binary
with the baked texture (or vertex colours, without one).

Axes: the PLY holds the frame's own coordinates. OBJ and glTF are y-up by convention, and the importers of Blender
(glTF, OBJ) and most DCC tools turn y-up into their z-up: so both are written in GLTF_FROM_ZUP's axes, (x, z, -y) of
the frame, and such an importer gets the frame's own coordinates back (a y-up viewer shows a z-up frame standing).

Materials: unlit-friendly and matte (no metal, no specular highlight: the texture already holds the light the photos
saw), two-sided (the surface is open where no photo saw it). glTF: metallicFactor 0, roughnessFactor 1, the PNG as
baseColorTexture; MTL: Kd 1 with map_Kd, no Ks.

Vertex colours: sRGB in the PLY and OBJ (as MeshLab and Blender read them); linear light in the glTF's COLOR_0, as
glTF specifies and its importers (Blender's included) read it. trimesh writes COLOR_0 as the bytes it is given, so
the glTF gets the colours converted to linear first (8 bits: the darkest shades step more coarsely than in sRGB).
"""
from __future__ import annotations

import io as bytes_io
from pathlib import Path

import numpy as np
import trimesh
from PIL import Image
from trimesh.exchange.obj import export_obj
from trimesh.exchange.ply import export_ply

from stages.common.media import GLTF_FROM_ZUP
from plenoxels.surface.texture import Texture

MATERIAL = "surface"
MTL = """# voxfield: the radiance field's colour baked into {texture} (light included), matte
newmtl {material}
Ka 0 0 0
Kd 1 1 1
Ks 0 0 0
Ns 0
d 1
illum 1
map_Kd {texture}
"""


def srgb_to_linear(c: np.ndarray) -> np.ndarray:
    """sRGB-encoded values in [0, 1] -> linear light."""
    return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)


def linear_to_srgb(c: np.ndarray) -> np.ndarray:
    """Linear light in [0, 1] -> sRGB-encoded values."""
    return np.where(c <= 0.0031308, 12.92 * c, 1.055 * np.maximum(c, 0.0031308) ** (1 / 2.4) - 0.055)


def textured(mesh: trimesh.Trimesh, texture: Texture) -> trimesh.Trimesh:
    """The mesh split along the atlas's seams, with its UVs, normals and a matte PBR material using the texture."""
    atlas = texture.atlas
    image = Image.fromarray(np.round(np.clip(texture.image, 0.0, 1.0) * 255).astype(np.uint8))
    material = trimesh.visual.material.PBRMaterial(name=MATERIAL, baseColorTexture=image, metallicFactor=0.0,
                                                   roughnessFactor=1.0, doubleSided=True)
    return trimesh.Trimesh(np.asarray(mesh.vertices)[atlas.vertex_map], atlas.faces,
                           vertex_normals=np.asarray(mesh.vertex_normals)[atlas.vertex_map],
                           visual=trimesh.visual.TextureVisuals(uv=atlas.uv, material=material), process=False)


def write_mesh_files(mesh: trimesh.Trimesh, folder: Path, texture: Texture | None = None) -> dict[str, str]:
    """mesh.ply (binary, normals and vertex colours); mesh.obj and mesh.glb, textured (mesh.mtl and mesh.png beside
    the OBJ, the PNG inside the GLB) when `texture` is given, else with vertex colours (module docstring for axes)."""
    folder = Path(folder)
    files = {"ply": "mesh.ply", "obj": "mesh.obj", "glb": "mesh.glb"}
    (folder / files["ply"]).write_bytes(export_ply(mesh, encoding="binary", vertex_normal=True))
    styled = textured(mesh, texture) if texture is not None else mesh.copy()
    styled.apply_transform(GLTF_FROM_ZUP)
    if texture is not None:
        files.update(mtl="mesh.mtl", png="mesh.png")
        text, _ = export_obj(styled, include_normals=True, include_texture=True, return_texture=True,
                             mtl_name=files["mtl"])
        (folder / files["obj"]).write_text(text)
        (folder / files["mtl"]).write_text(MTL.format(material=MATERIAL, texture=files["png"]))
        buffer = bytes_io.BytesIO()
        styled.visual.material.baseColorTexture.save(buffer, format="PNG")
        (folder / files["png"]).write_bytes(buffer.getvalue())
    else:
        (folder / files["obj"]).write_text(export_obj(styled, include_normals=True, include_color=True))
        linear = srgb_to_linear(styled.visual.vertex_colors[:, :3] / 255.0)
        styled.visual.vertex_colors[:, :3] = np.round(linear * 255.0).astype(np.uint8)
    styled.export(folder / files["glb"])
    return files
