"""Runs inside Blender's Python (the `bpy` module in its own environment, bench/blender.py starts it): imports each
exported file as a Blender user's File > Import does, with the importer's defaults, and writes what arrived as JSON:
objects, counts, world-space bounds and a sample of vertex positions, the materials' node wiring (what feeds the
Principled BSDF's Base Color, the image it reads), the colour attributes and a sample of their values per vertex; and, given a
camera, a Cycles render of what the material's Base Color shows (its source wired into an Emission shader, no lights,
the Standard view transform, so pixels are the texture's or the vertex colours' own sRGB values).

    python blender_session.py SPEC.json    (SPEC: {"files": {kind: path}, "camera": {...} | null, "out": dir})

No project imports: this runs with Blender's NumPy, not the project's.
"""
import json
import sys
from pathlib import Path

import bpy
import numpy as np
from mathutils import Matrix

SAMPLE_VERTICES = 4000
IMPORTERS = {
    "glb": lambda path: bpy.ops.import_scene.gltf(filepath=path),
    "obj": lambda path: bpy.ops.wm.obj_import(filepath=path),
    "ply": lambda path: bpy.ops.wm.ply_import(filepath=path),
}


def world_vertices(obj) -> np.ndarray:
    co = np.zeros(len(obj.data.vertices) * 3)
    obj.data.vertices.foreach_get("co", co)
    co = co.reshape(-1, 3)
    matrix = np.array(obj.matrix_world)
    return co @ matrix[:3, :3].T + matrix[:3, 3]


def material_report(material) -> dict:
    report = {"name": material.name, "base_color_from": None, "image": None, "metallic": None, "roughness": None}
    if not material.use_nodes:
        return report
    for node in material.node_tree.nodes:
        if node.type != "BSDF_PRINCIPLED":
            continue
        report["metallic"] = float(node.inputs["Metallic"].default_value)
        report["roughness"] = float(node.inputs["Roughness"].default_value)
        links = node.inputs["Base Color"].links
        if links:
            source = links[0].from_node
            report["base_color_from"] = source.type
            if source.type == "TEX_IMAGE" and source.image is not None:
                image = source.image
                report["image"] = {"name": image.name, "size": list(image.size), "packed": image.packed_file is not None,
                                   "filepath": bpy.path.abspath(image.filepath) if image.filepath else "",
                                   "colorspace": image.colorspace_settings.name}
    return report


def colour_report(mesh, sample: np.ndarray) -> list[dict]:
    found = []
    for index, attribute in enumerate(mesh.color_attributes):
        entry = {"name": attribute.name, "domain": attribute.domain, "data_type": attribute.data_type,
                 "render_active": index == mesh.color_attributes.render_color_index}
        if attribute.domain in ("POINT", "CORNER"):
            srgb = np.zeros(len(attribute.data) * 4)
            attribute.data.foreach_get("color_srgb", srgb)
            srgb = srgb.reshape(-1, 4)
            if attribute.domain == "CORNER":  # glTF's importer: each vertex's colour on every corner it is
                vertex_of_corner = np.zeros(len(mesh.loops), dtype=np.int64)
                mesh.loops.foreach_get("vertex_index", vertex_of_corner)
                per_vertex = np.zeros((len(mesh.vertices), 4))
                per_vertex[vertex_of_corner] = srgb
                srgb = per_vertex
            entry["sample_srgb"] = srgb[sample, :3].tolist()
        found.append(entry)
    return found


def emission_wiring(obj) -> None:
    """Every material's Base Color source (or, with no material, the render colour attribute) into an Emission
    shader that feeds the output: the render shows the colours themselves, unlit."""
    mesh = obj.data
    if not mesh.materials:
        material = bpy.data.materials.new("vertex colours")
        material.use_nodes = True
        nodes = material.node_tree.nodes
        attribute = nodes.new("ShaderNodeVertexColor")
        attribute.layer_name = mesh.color_attributes[mesh.color_attributes.render_color_index].name
        source = attribute.outputs["Color"]
        mesh.materials.append(material)
        materials = [(material, source)]
    else:
        materials = []
        for material in mesh.materials:
            principled = next(n for n in material.node_tree.nodes if n.type == "BSDF_PRINCIPLED")
            base = principled.inputs["Base Color"]
            materials.append((material, base.links[0].from_socket if base.links else None))
    for material, source in materials:
        tree = material.node_tree
        emission = tree.nodes.new("ShaderNodeEmission")
        if source is not None:
            tree.links.new(source, emission.inputs["Color"])
        output = next(n for n in tree.nodes if n.type == "OUTPUT_MATERIAL")
        tree.links.new(emission.outputs["Emission"], output.inputs["Surface"])


def render(camera: dict, path: Path) -> None:
    scene = bpy.context.scene
    scene.render.engine = "CYCLES"
    scene.cycles.device = "CPU"
    scene.cycles.samples = camera.get("samples", 4)
    scene.cycles.use_denoising = False
    scene.cycles.filter_width = 0.01  # each pixel its centre's colour, as plenoxels.surface.texture.render_mesh draws it
    scene.render.resolution_x, scene.render.resolution_y = camera["w"], camera["h"]
    scene.render.resolution_percentage = 100
    scene.render.film_transparent = True
    scene.view_settings.view_transform = "Standard"
    scene.view_settings.look = "None"
    scene.render.image_settings.file_format = "PNG"
    scene.render.image_settings.color_mode = "RGBA"
    data = bpy.data.cameras.new("training view")
    data.sensor_fit = "HORIZONTAL"
    data.sensor_width = 36.0
    data.lens = camera["fl_x"] * data.sensor_width / camera["w"]
    data.shift_x = (camera["w"] / 2 - camera["cx"]) / camera["w"]
    data.shift_y = (camera["cy"] - camera["h"] / 2) / camera["w"]
    data.clip_start, data.clip_end = 1e-3, 1e6
    view = bpy.data.objects.new("training view", data)
    scene.collection.objects.link(view)
    view.matrix_world = Matrix(camera["c2w"])  # OpenGL camera-to-world: Blender's cameras look down -z, y up, too
    scene.camera = view
    scene.render.filepath = str(path)
    bpy.ops.render.render(write_still=True)


def main(spec_path: str) -> None:
    spec = json.loads(Path(spec_path).read_text())
    out = Path(spec["out"])
    report = {"blender": bpy.app.version_string, "files": {}}
    for kind, path in spec["files"].items():
        bpy.ops.wm.read_factory_settings(use_empty=True)
        IMPORTERS[kind](path)
        meshes = [o for o in bpy.context.scene.objects if o.type == "MESH"]
        entry = {"objects": len(meshes), "vertices": 0, "faces": 0, "materials": [], "colour_attributes": [],
                 "uv_layers": [], "positions": []}
        for obj in meshes:
            mesh = obj.data
            world = world_vertices(obj)
            sample = np.linspace(0, len(world) - 1, min(SAMPLE_VERTICES, len(world))).round().astype(int)
            entry["vertices"] += len(mesh.vertices)
            entry["faces"] += len(mesh.polygons)
            entry["bounds"] = [world.min(axis=0).tolist(), world.max(axis=0).tolist()]
            entry["positions"] += world[sample].tolist()
            entry["uv_layers"] += [layer.name for layer in mesh.uv_layers]
            entry["materials"] += [material_report(m) for m in mesh.materials if m is not None]
            entry["colour_attributes"] += colour_report(mesh, sample)
        if spec.get("camera") and len(meshes) == 1:
            emission_wiring(meshes[0])
            render(spec["camera"], out / f"{kind}.png")
            entry["render"] = str(out / f"{kind}.png")
        report["files"][kind] = entry
    (out / "report.json").write_text(json.dumps(report))


if __name__ == "__main__":
    main(sys.argv[1])
