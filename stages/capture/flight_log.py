"""Where a drone was as it filmed: the flight log DJI writes beside a clip, a subtitle file of its name (.SRT, where
the drone's video captions are on), each caption a span of the clip's time (a frame's, or a second's) and what the
drone read then. Its positions let the clip's frames be held near where they were taken, as a survey's photos are by
their EXIF (stages/sfm/gps.py).

Captions come in two families. Current drones label each value (`[latitude: 47.376901] [longitude: 8.541701]
[rel_alt: 30.100 abs_alt: 438.100]`, a few firmwares spelling it `longtitude`); older ones and the enterprise lines
write an unlabelled tuple (`GPS(8.5417,47.3769,14) BAROMETER:30.1`, `GPS (8.5417, 47.3769, 15), ... H 30.10m`) whose
order differs between models (longitude first on a Mavic Pro or a Phantom 4 RTK, latitude first on a Matrice 300),
so a tuple is read only where one of its values is past 90 degrees and so must be the longitude. Their heights are
above the take-off (the barometer's); current drones' `abs_alt` above the sea, which is taken where written. Some tuples
round their degrees to 4 places (11 m), which each position says (`rounding_m`: the standard deviation of an error
spread evenly across its last digit)."""
from __future__ import annotations

import math
import re
from pathlib import Path

import numpy as np

from stages.capture.video import frame_seconds

SUFFIXES = (".srt", ".SRT", ".Srt")
# Metres of latitude in a degree, for what a position's last written digit spans.
METRES_PER_DEGREE = 111_320.0

_NUMBER = r"([-+]?\d+(?:\.(\d+))?)"
_TIME = r"(\d+):(\d+):(\d+)[,.](\d+)"
_SPAN = re.compile(rf"{_TIME}\s*-->\s*{_TIME}")
_LABELLED = re.compile(rf"\[\s*latitude\s*:\s*{_NUMBER}\s*\]\s*\[\s*longt?itude\s*:\s*{_NUMBER}\s*\]", re.I)
_TUPLE = re.compile(rf"GPS\s*\(\s*{_NUMBER}\s*,\s*{_NUMBER}\s*[,)]", re.I)
# Heights in the order they are taken: above the sea where written, else above the take-off.
_HEIGHTS = (re.compile(rf"abs_alt\s*:\s*{_NUMBER}", re.I), re.compile(rf"\[\s*altitude\s*:\s*{_NUMBER}", re.I),
            re.compile(rf"rel_alt\s*:\s*{_NUMBER}", re.I), re.compile(rf"BAROMETER\s*[:(]\s*{_NUMBER}", re.I),
            re.compile(rf"(?:^|[\s,])H[\s=:]+{_NUMBER}\s*m", re.I))


def flight_log(clip: Path) -> Path | None:
    """The subtitle file beside `clip` with its name, where there is one."""
    for suffix in SUFFIXES:
        if (log := clip.with_suffix(suffix)).is_file():
            return log
    return None


def read_track(log: Path) -> dict:
    """The drone's positions over the clip: `seconds` [N] (the middle of each caption's span; `step` apart, the median),
    `positions` [N, 3] (latitude, longitude in degrees, height in metres), `height` (which height: "sea" or
    "take-off"), `rounding_m` (what the degrees' last written digit leaves unsaid, metres across); or `why` where the
    file gives none."""
    text = log.read_text(encoding="utf-8", errors="replace")
    captions = [c for c in re.split(r"\n\s*\n", text.replace("\r\n", "\n")) if _SPAN.search(c)]
    if not any(_LABELLED.search(c) or _TUPLE.search(c) for c in captions):  # a film's subtitles, say
        return {"why": f"{log.name} gives no positions"}
    for rank, height in enumerate(_HEIGHTS):  # one kind of height for the whole clip, the first every caption has
        if all(height.search(c) for c in captions):
            break
    else:
        return {"why": f"{log.name} gives no height"}
    seconds, positions, places = [], [], 0
    for caption in captions:
        span = _SPAN.search(caption).groups()
        where = place(caption)
        if where is None:
            continue
        latitude, longitude, written = where
        if latitude == longitude == 0.0:  # no fix yet
            continue
        seconds.append((clock(span[:4]) + clock(span[4:])) / 2.0)
        positions.append((latitude, longitude, float(height.search(caption).group(1))))
        places = max(places, written)
    if len(positions) < 2:
        tuples = not any(_LABELLED.search(c) for c in captions)
        return {"why": f"{log.name}'s GPS does not say which of its values is the latitude" if tuples
                else f"{log.name} gives no positions"}
    order = np.argsort(seconds, kind="stable")
    return {"seconds": np.asarray(seconds)[order], "positions": np.asarray(positions)[order],
            "step": float(np.median(np.diff(np.asarray(seconds)[order]))),
            "height": "sea" if rank == 0 else "take-off",
            "rounding_m": round(METRES_PER_DEGREE * 10.0 ** -places / math.sqrt(12.0), 3)}


def clock(parts: tuple[str, ...]) -> float:
    """Seconds from a subtitle's hours, minutes, seconds and fraction."""
    hours, minutes, whole, fraction = parts
    return int(hours) * 3600 + int(minutes) * 60 + int(whole) + float(f"0.{fraction}")


def place(caption: str) -> tuple[float, float, int] | None:
    """A caption's latitude and longitude and the decimal places they were written to; None where it has none, or
    gives an unlabelled pair whose order cannot be told."""
    if found := _LABELLED.search(caption):
        latitude, lat_places, longitude, lon_places = found.groups()
    elif found := _TUPLE.search(caption):
        first, first_places, second, second_places = found.groups()
        if abs(float(first)) > 90.0 >= abs(float(second)):
            longitude, lon_places, latitude, lat_places = first, first_places, second, second_places
        elif abs(float(second)) > 90.0 >= abs(float(first)):
            latitude, lat_places, longitude, lon_places = first, first_places, second, second_places
        else:
            return None
    else:
        return None
    latitude, longitude = float(latitude), float(longitude)
    if not (abs(latitude) <= 90.0 and abs(longitude) <= 180.0 and math.isfinite(latitude + longitude)):
        return None
    return latitude, longitude, min(len(lat_places or ""), len(lon_places or ""))


def position_at(track: dict, seconds: float) -> list[float] | None:
    """Where the drone was `seconds` into the clip, between the captions around it; None outside the log's span (a
    caption's length past either end)."""
    times, step = track["seconds"], track["step"]
    if not times[0] - step <= seconds <= times[-1] + step:
        return None
    return [float(np.interp(seconds, times, track["positions"][:, axis])) for axis in range(3)]


def locate_frames(records: list[dict], clip: Path, fps: float) -> dict | None:
    """Each frame's place from the clip's flight log, where it has one: its record's `gps` (`position`: latitude,
    longitude, height; `rounding_m`; `height`: "sea" or "take-off"). Returns what was read for the summary
    (`file`, `frames` located; or `why` none were), None without a log."""
    log = flight_log(clip)
    if log is None:
        return None
    try:
        track = read_track(log)
    except OSError as error:  # unreadable where it lies: the frames are posed without it, as without a log
        track = {"why": f"{log.name} could not be read ({error.strerror or error})"}
    if "why" in track:
        return {"file": log.name, "why": track["why"]}
    located = 0
    for record in records:
        if (position := position_at(track, frame_seconds(record["name"], fps))) is not None:
            record["gps"] = {"position": position, "rounding_m": track["rounding_m"], "height": track["height"]}
            located += 1
    return {"file": log.name, "frames": located, "rounding_m": track["rounding_m"], "height": track["height"]}
