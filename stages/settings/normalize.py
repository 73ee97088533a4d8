"""The normalize stage as the pipeline plans it: its name, the stages it reads, its version and its settings (its
work: stages/normalize.py)."""
from __future__ import annotations

from dataclasses import dataclass

from stages.framing.options import SceneOptions

NAME = "normalize"
DEPENDS: tuple[str, ...] = ("poses",)
VERSION = 1


@dataclass
class Settings(SceneOptions):
    """The scene frame's options (stages.framing.options.SceneOptions, which checks them); normalize has no others."""
