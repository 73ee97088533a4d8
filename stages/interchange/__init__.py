"""Files for other tools: meshes (OBJ, glTF, PLY) and point clouds (export)."""
