"""Settings: one typed dataclass per stage, filled from a YAML preset, a scene-type overlay and
command-line overrides, validated on load.

Resolution order (later wins): the dataclass defaults, `configs/<preset>.yaml`,
`configs/scene_types/<type>.yaml` (only for stages after `normalize`, once the scene type is known; its
`presets.<preset>` section last, for what pays for one scene type at one preset only), then
`--set section.key=value` overrides. A stage's section in the YAML is its name.

Each Settings field's help is the one-line string right below it (an attribute docstring, as in PEP 257 and tyro);
`field_help` reads them and `python -m pipeline settings` prints them.
"""
from __future__ import annotations

import ast
import dataclasses
import inspect
import math
import textwrap
import types
import typing
from pathlib import Path
from typing import Any, Literal

import yaml

from plenoxels.core.errors import UserError

CONFIG_DIR = Path(__file__).resolve().parent.parent / "configs"


def preset_names() -> list[str]:
    return sorted(p.stem for p in CONFIG_DIR.glob("*.yaml"))


def _read_yaml(path: Path) -> dict[str, dict[str, Any]]:
    try:
        data = yaml.safe_load(path.read_text()) or {}
    except yaml.YAMLError as e:
        raise UserError(f"{path} is not valid YAML ({e.__class__.__name__}); fix the file") from None
    if not isinstance(data, dict) or not all(isinstance(v, dict) for v in data.values()):
        raise UserError(f"{path} must map stage names to sections of key: value settings")
    return data


def load_preset(name: str) -> dict[str, dict[str, Any]]:
    path = CONFIG_DIR / f"{name}.yaml"
    if not path.is_file():
        raise UserError(f"unknown preset '{name}'; choose one of: {', '.join(preset_names())}")
    return _read_yaml(path)


def load_scene_type_overlay(scene_type: str | None, preset: str) -> dict[str, dict[str, Any]]:
    """What `configs/scene_types/<scene_type>.yaml` sets at `preset`: its stage sections, then its
    `presets.<preset>` section's."""
    if scene_type is None:
        return {}
    path = CONFIG_DIR / "scene_types" / f"{scene_type}.yaml"
    if not path.is_file():
        return {}
    overlay = _read_yaml(path)
    by_preset = overlay.pop("presets", {})
    for name, sections in by_preset.items():
        if name not in preset_names():
            raise UserError(f"{path}: presets.{name} names no preset; presets are: {', '.join(preset_names())}")
        if not isinstance(sections, dict) or not all(isinstance(v, dict) for v in sections.values()):
            raise UserError(f"{path}: presets.{name} must map stage names to sections of key: value settings")
    return merge(overlay, by_preset.get(preset) or {})


def parse_overrides(pairs: list[str]) -> dict[str, dict[str, Any]]:
    """['fit.sh_degree=1', 'ingest.max_side=800'] -> {'fit': {'sh_degree': 1}, 'ingest': {'max_side': 800}}.
    Values are read as YAML scalars/lists, so 1 is an int, 0.5 a float, [128, 256] a list, auto a string."""
    out: dict[str, dict[str, Any]] = {}
    for pair in pairs:
        key, sep, raw = pair.partition("=")
        section, dot, name = key.strip().partition(".")
        if not sep or not dot or not section or not name:
            raise UserError(f"--set '{pair}' must look like section.key=value (for example fit.sh_degree=1)")
        try:
            value = yaml.safe_load(raw) if raw.strip() else ""
        except yaml.YAMLError:
            value = raw
        out.setdefault(section, {})[name] = value
    return out


def merge(*layers: dict[str, dict[str, Any]]) -> dict[str, dict[str, Any]]:
    merged: dict[str, dict[str, Any]] = {}
    for layer in layers:
        for section, values in layer.items():
            merged.setdefault(section, {}).update(values)
    return merged


def _type_name(tp: Any) -> str:
    origin = typing.get_origin(tp)
    if origin is Literal:
        return "one of " + ", ".join(repr(a) for a in typing.get_args(tp))
    if origin in (typing.Union, types.UnionType):
        return " or ".join(_type_name(a) for a in typing.get_args(tp))
    if origin in (list, tuple):
        return f"a list of {_type_name(typing.get_args(tp)[0])}"
    return "null" if tp is type(None) else getattr(tp, "__name__", str(tp))


def _coerce(value: Any, tp: Any) -> Any:
    """Returns value as type tp, or raises ValueError. Only safe widenings (int -> float, list -> tuple)."""
    origin = typing.get_origin(tp)
    if origin is Literal:
        allowed = typing.get_args(tp)
        # YAML 1.1 reads on/off and yes/no as booleans; where a setting spells them as words, give the words back.
        if isinstance(value, bool):
            for word in (("on", "yes", "true") if value else ("off", "no", "false")):
                if word in allowed:
                    return word
        if value in allowed:
            return value
        raise ValueError
    if origin in (typing.Union, types.UnionType):
        for arg in typing.get_args(tp):
            try:
                return _coerce(value, arg)
            except ValueError:
                continue
        raise ValueError
    if origin in (list, tuple):
        if not isinstance(value, (list, tuple)):
            value = [value]
        inner = typing.get_args(tp)[0]
        items = [_coerce(v, inner) for v in value]
        return tuple(items) if origin is tuple else items
    if tp is type(None):
        if value is None:
            return None
        raise ValueError
    if tp is bool:
        if isinstance(value, bool):
            return value
        raise ValueError
    if tp is int:
        if isinstance(value, int) and not isinstance(value, bool):
            return value
        raise ValueError
    if tp is float:
        if isinstance(value, (int, float)) and not isinstance(value, bool):
            return float(value)
        if isinstance(value, str):  # YAML 1.1 reads 5e-6 (no dot) as a string
            number = float(value)  # ValueError for words
            if math.isfinite(number):
                return number
        raise ValueError
    if tp is str:
        if isinstance(value, str):
            return value
        raise ValueError
    raise ValueError


def build(cls: type, section: str, values: dict[str, Any]):
    """Builds settings dataclass `cls` from `values`, with one-line errors naming the key and what is allowed.
    Types are checked here; values by the dataclass's `check(self) -> None`, when it has one, which raises a one-line
    UserError naming the key (a stage's check runs those of the options classes its Settings extend, then its own)."""
    fields = {f.name: f for f in dataclasses.fields(cls)}
    hints = typing.get_type_hints(cls)
    kwargs = {}
    for key, value in values.items():
        if key not in fields:
            raise UserError(f"unknown setting '{section}.{key}'; allowed: {', '.join(sorted(fields)) or 'none'}")
        try:
            kwargs[key] = _coerce(value, hints[key])
        except ValueError:
            raise UserError(f"bad value {value!r} for '{section}.{key}': expected {_type_name(hints[key])}") from None
    settings = cls(**kwargs)
    if hasattr(settings, "check"):
        settings.check()
    return settings


def to_dict(settings) -> dict[str, Any]:
    return dataclasses.asdict(settings)


def field_help(cls: type) -> dict[str, str]:
    """Field name -> its attribute docstring (the string literal on the line after the field), for `cls` and the
    dataclasses it inherits from. Fields without one are absent."""
    found: dict[str, str] = {}
    for klass in reversed([k for k in cls.__mro__ if dataclasses.is_dataclass(k)]):
        tree = ast.parse(textwrap.dedent(inspect.getsource(klass)))
        body = next(node for node in tree.body if isinstance(node, ast.ClassDef)).body
        for node, after in zip(body, body[1:]):
            if (isinstance(node, ast.AnnAssign) and isinstance(node.target, ast.Name) and isinstance(after, ast.Expr)
                    and isinstance(after.value, ast.Constant) and isinstance(after.value.value, str)):
                found[node.target.id] = " ".join(after.value.value.split())
    return found


@dataclasses.dataclass(frozen=True)
class SettingInfo:
    """One setting as `python -m pipeline settings` shows it."""
    name: str
    type: str
    default: Any
    preset_value: Any          # what the chosen preset gives (the default when it does not set it)
    scene_types: dict[str, Any]  # scene type -> value its overlay gives, for the types that set this one
    help: str | None


def _default(f: dataclasses.Field) -> Any:
    if f.default is not dataclasses.MISSING:
        return f.default
    if f.default_factory is not dataclasses.MISSING:
        return f.default_factory()
    return None


def describe(cls: type, section: str, preset: str = "default") -> list[SettingInfo]:
    """Every setting of the stage `section` whose Settings dataclass is `cls`, in field order."""
    hints = typing.get_type_hints(cls)
    helps = field_help(cls)
    preset_values = load_preset(preset).get(section, {})
    overlays = {p.stem: load_scene_type_overlay(p.stem, preset).get(section, {})
                for p in sorted((CONFIG_DIR / "scene_types").glob("*.yaml"))}
    infos = []
    for f in dataclasses.fields(cls):
        default = _default(f)
        infos.append(SettingInfo(
            f.name, _type_name(hints[f.name]), default, preset_values.get(f.name, default),
            {kind: values[f.name] for kind, values in overlays.items() if f.name in values}, helps.get(f.name)))
    return infos


def format_settings(section: str, infos: list[SettingInfo], preset: str) -> str:
    lines = [f"{section}:"]
    for info in infos:
        line = f"  {section}.{info.name} ({info.type}) = {info.default!r}"
        if info.preset_value != info.default:
            line += f"; preset {preset}: {info.preset_value!r}"
        for kind, value in info.scene_types.items():
            line += f"; {kind} scenes: {value!r}"
        lines.append(line)
        lines.append(f"      {info.help or '(no help yet)'}")
    return "\n".join(lines)
