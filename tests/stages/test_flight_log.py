"""A drone's flight log beside its clip (DJI's subtitle file): which of its forms are read, how their positions fall
on the clip's frames, and which are refused because their order cannot be told."""
from __future__ import annotations

import math

import numpy as np
import pytest

from stages.capture.flight_log import (METRES_PER_DEGREE, flight_log, locate_frames, place, position_at,
                                       read_track)


def srt_time(seconds: float) -> str:
    ms = round(seconds * 1000)
    return f"{ms // 3_600_000:02d}:{ms // 60_000 % 60:02d}:{ms // 1000 % 60:02d},{ms % 1000:03d}"


def caption(number: int, start: float, end: float, body: str) -> str:
    return f"{number}\n{srt_time(start)} --> {srt_time(end)}\n{body}\n"


def labelled(latitude: float, longitude: float, rel: float, sea: float, spelling: str = "longitude") -> str:
    """A current DJI drone's caption (Mini 4 Pro, Air 3S, Mavic 3), its values labelled."""
    return (f'<font size="28">FrameCnt: 1, DiffTime: 33ms\n2026-05-27 13:14:22.911\n[iso: 200] [shutter: 1/6400.0] '
            f"[fnum: 1.8] [focal_len: 24.00] [latitude: {latitude:.6f}] [{spelling}: {longitude:.6f}] "
            f"[rel_alt: {rel:.3f} abs_alt: {sea:.3f}] [ct: 5263] </font>")


def tuple_form(first: float, second: float, barometer: float) -> str:
    """An older DJI drone's caption (a Mavic Pro's): an unlabelled GPS tuple to four places, height from its
    barometer."""
    return (f"HOME({first:.4f},{second:.4f}) 2017.07.29 15:18:50\nGPS({first:.4f},{second:.4f},14) "
            f"BAROMETER:{barometer:.1f}\nISO:100 Shutter:60 EV: Fnum:2.2 ")


def test_a_current_drones_labelled_log_gives_each_frame_its_place_above_the_sea(tmp_path):
    fps = 30.0
    places = [(47.3769 + 1e-5 * i, 8.5417 - 2e-5 * i, 30.0 + 0.1 * i) for i in range(60)]
    spellings = ["longitude", "longtitude"]  # a few firmwares misspell it
    (tmp_path / "DJI_0001.SRT").write_text("\n".join(
        caption(i + 1, i / fps, (i + 1) / fps, labelled(lat, lon, rel, 400.0 + rel, spellings[i % 2]))
        for i, (lat, lon, rel) in enumerate(places)), newline="\r\n")  # as Windows tools save it
    clip = tmp_path / "DJI_0001.MP4"
    assert flight_log(clip) == tmp_path / "DJI_0001.SRT"
    records = [{"name": f"frame_{index:06d}"} for index in (0, 17, 59)] + [{"name": "frame_000400"}]
    found = locate_frames(records, clip, fps)
    assert found["frames"] == 3 and found["height"] == "sea" and found["rounding_m"] < 0.05
    for record in records[:3]:
        lat, lon, rel = places[int(record["name"][6:])]
        # its own caption's place, but for the subtitles' times rounded to milliseconds (a centimetre here)
        assert record["gps"]["position"][:2] == pytest.approx([lat, lon], abs=1e-7)
        assert record["gps"]["position"][2] == pytest.approx(400.0 + rel, abs=0.01)
    assert "gps" not in records[3]  # past the log's end: no place


def test_an_older_drones_tuple_is_read_where_a_value_past_90_degrees_says_its_order(tmp_path):
    """A Mavic Pro over Uluru writes longitude first, one caption a second: a frame between two captions lies
    between their places, its height from the barometer (above the take-off), its place rounded to 11 m."""
    log = tmp_path / "DJI_0003.SRT"
    log.write_text("\n".join(caption(i + 1, i + 1.0, i + 2.0, tuple_form(131.1660 + 1e-4 * i, -25.2088, 2.0 * i))
                             for i in range(5)))
    track = read_track(log)
    assert track["height"] == "take-off"
    assert track["rounding_m"] == pytest.approx(METRES_PER_DEGREE * 1e-4 / math.sqrt(12.0), rel=1e-3)
    assert position_at(track, 2.5) == pytest.approx([-25.2088, 131.1661, 2.0])  # the middle of its second
    assert position_at(track, 3.0) == pytest.approx([-25.2088, 131.16615, 3.0])
    assert position_at(track, 0.5) is not None and position_at(track, 7.5) is None
    # latitude first (a Matrice 300's order) is told the same way
    assert place("GPS(-25.2088,131.1660,0.0M) BAROMETER:0.3M") == (-25.2088, 131.1660, 4)


def test_a_tuple_whose_order_cannot_be_told_is_not_read_and_says_why(tmp_path):
    """Near Zurich both values lie under 90 degrees, and models write them in either order: a wrong guess mirrors the
    flight, which a similarity can fit upside down, so the log is left unread."""
    assert place("GPS(8.5417,47.3769,14) BAROMETER:2.0") is None
    log = tmp_path / "DJI_0004.SRT"
    log.write_text("\n".join(caption(i + 1, i, i + 1.0, tuple_form(8.5417 + 1e-4 * i, 47.3769, i)) for i in range(4)))
    records = [{"name": "frame_000000"}]
    found = locate_frames(records, tmp_path / "DJI_0004.MP4", 30.0)
    assert "which of its values is the latitude" in found["why"] and "gps" not in records[0]


def test_captions_without_a_fix_are_left_out_and_a_log_without_heights_gives_none(tmp_path):
    log = tmp_path / "a.srt"
    bodies = [labelled(0.0, 0.0, 0.0, 0.0)] + [labelled(47.3769 + 1e-5 * i, 8.5417, i, 400.0 + i) for i in range(1, 4)]
    log.write_text("\n".join(caption(i + 1, i, i + 1.0, body) for i, body in enumerate(bodies)))
    track = read_track(log)
    np.testing.assert_allclose(track["seconds"], [1.5, 2.5, 3.5])
    assert track["positions"][:, 0].min() > 47.0
    log.write_text(caption(1, 0, 1, "[latitude: 47.3769] [longitude: 8.5417]") + "\n"
                   + caption(2, 1, 2, "[latitude: 47.3770] [longitude: 8.5417]"))
    assert "no height" in read_track(log)["why"]
    log.write_text(caption(1, 0, 1, "Where were you?") + "\n" + caption(2, 1, 2, "Filming."))  # a film's subtitles
    assert "gives no positions" in read_track(log)["why"]
    log.write_bytes(bytes(range(256)) * 8)  # not text at all
    assert "gives no positions" in read_track(log)["why"]
    assert flight_log(tmp_path / "b.mp4") is None
    (tmp_path / "c.SRT").mkdir()  # a folder of its name, which no reader can open as a file
    assert flight_log(tmp_path / "c.mp4") is None


def test_a_log_that_cannot_be_read_leaves_the_frames_unplaced_and_says_why(tmp_path, monkeypatch):
    import stages.capture.flight_log as module

    (tmp_path / "DJI_0006.SRT").write_text(caption(1, 0, 1, labelled(47.3769, 8.5417, 1.0, 401.0)))

    def refused(log):
        raise PermissionError(13, "Permission denied", str(log))
    monkeypatch.setattr(module, "read_track", refused)
    records = [{"name": "frame_000000"}]
    found = locate_frames(records, tmp_path / "DJI_0006.MP4", 30.0)
    assert found["why"] == "DJI_0006.SRT could not be read (Permission denied)" and "gps" not in records[0]
