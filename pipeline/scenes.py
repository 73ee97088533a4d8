"""Where a scene's outputs go: its name from the path of its photos, and scene lists for a batch."""
from __future__ import annotations

from pathlib import Path

from plenoxels.core.errors import UserError
from stages.common.text import text_name

GENERIC_FOLDER_NAMES = {"images", "photos", "frames", "input", "rgb"}
SCENE_LIST_SUFFIXES = {".txt", ".list"}


def scene_name(scene: Path) -> str:
    """fox/images -> 'fox', fern/images_4 -> 'fern', my_trip.mp4 -> 'my_trip'."""
    scene = scene.resolve()
    name = scene.stem if scene.is_file() else scene.name
    if name.lower() in GENERIC_FOLDER_NAMES or name.lower().startswith("images_"):
        name = scene.parent.name
    return text_name(name) or "scene"


def read_scene_list(items: list[Path]) -> list[Path]:
    """Scene folders (or videos) from the command line, in order, without repeats; a `.txt` or `.list` file
    stands for the scenes it lists, one a line (blank lines and `#` comments skipped, relative paths from the
    list's own folder)."""
    scenes: list[Path] = []
    for item in items:
        if item.suffix.lower() in SCENE_LIST_SUFFIXES and item.is_file():
            for line in item.read_text().splitlines():
                entry = line.split("#", 1)[0].strip()
                if entry:
                    scenes.append(item.parent / entry)
        elif item.suffix.lower() in SCENE_LIST_SUFFIXES and not item.exists():
            raise UserError(f"scene list {item} does not exist")
        else:
            scenes.append(item)
    unique = list(dict.fromkeys(s.resolve() for s in scenes))
    if not unique:
        raise UserError("no scenes given: name scene folders, or a .txt file listing them one a line")
    return unique


def output_names(scenes: list[Path]) -> list[str]:
    """One output folder name per scene: its `scene_name`, with -2, -3 ... added where two scenes share one."""
    names, taken = [], set()
    for scene in scenes:
        base = name = scene_name(scene)
        suffix = 2
        while name in taken:
            name, suffix = f"{base}-{suffix}", suffix + 1
        taken.add(name)
        names.append(name)
    return names
