"""Words and numbers as a person reads them in the pipeline's lines: short lists, durations, sizes, counts; and a
duration setting read back into seconds."""
from __future__ import annotations

import math
import re
from collections import Counter
from typing import Any

from plenoxels.core.errors import UserError

NAMES_SHOWN = 8  # names shown before 'and N more'


def short_list(names: list[str]) -> str:
    """The first NAMES_SHOWN names, comma-separated, and how many more there are."""
    shown = ", ".join(names[:NAMES_SHOWN])
    return shown + (f" and {len(names) - NAMES_SHOWN} more" if len(names) > NAMES_SHOWN else "")


def format_duration(seconds: float) -> str:
    """'2m05s', or '45s' under a minute."""
    minutes, sec = divmod(int(round(seconds)), 60)
    return f"{minutes}m{sec:02d}s" if minutes else f"{sec}s"


def format_bytes(n: int) -> str:
    """A byte count as '22 MB', or '640 kB' under a megabyte."""
    return f"{n / 1e6:.0f} MB" if n >= 1e6 else f"{n / 1e3:.0f} kB"


def format_count(n: int) -> str:
    """A large count as '1.25M', or '146.9k' under a million."""
    return f"{n / 1e6:.2f}M" if n >= 1e6 else f"{n / 1e3:.1f}k"


_DURATION_PART = re.compile(r"(\d+(?:\.\d*)?|\.\d+)([hms])")
_DURATION_UNITS = {"h": 3600.0, "m": 60.0, "s": 1.0}


def parse_duration(value: Any, key: str) -> float:
    """Seconds in a duration setting: a number of seconds (90, 12.5), or hours, minutes and seconds written as
    '1h', '5m', '90s', '2m30s' (units in that order, each at most once); 0 or '' is 0 (off). A bad value is a
    UserError naming `key`."""
    bad = UserError(f"bad value {value!r} for '{key}': expected a duration such as 90s, 5m, 2m30s or a number of "
                    f"seconds (0: off)")
    if isinstance(value, (int, float)) and not isinstance(value, bool):
        seconds = float(value)
    elif isinstance(value, str):
        text = value.strip().lower().replace(" ", "")
        try:
            seconds = float(text) if text else 0.0
        except ValueError:
            parts = list(_DURATION_PART.finditer(text))
            units = [p.group(2) for p in parts]
            if not parts or "".join(p.group(0) for p in parts) != text or units != sorted(set(units), key="hms".index):
                raise bad from None
            seconds = sum(float(p.group(1)) * _DURATION_UNITS[p.group(2)] for p in parts)
    else:
        raise bad
    if not math.isfinite(seconds) or seconds < 0:
        raise UserError(f"bad value {value!r} for '{key}': a duration must be a finite number of seconds >= 0")
    return seconds


def text_name(name: str) -> str:
    """A file name as text every tool takes: the bytes of a name that are not UTF-8 (written by another system's
    encoding, which Python keeps as lone surrogates) as %XX, the rest as it is."""
    try:
        name.encode("utf-8")
        return name
    except UnicodeEncodeError:
        escaped = name.encode("utf-8", "surrogateescape").decode("utf-8", "backslashreplace")
        return escaped.replace("\\x", "%")


def size_words(records: list[dict]) -> str:
    """The photos' sizes: '640x480', or the most common first with their counts where they differ (portrait and
    landscape photos mixed, two cameras)."""
    sizes = Counter(f"{r['width']}x{r['height']}" for r in records).most_common()
    if len(sizes) == 1:
        return sizes[0][0]
    shown = ", ".join(f"{size} ({count})" for size, count in sizes[:3])
    return shown + (f" and {len(sizes) - 3} other sizes" if len(sizes) > 3 else "")
