"""The viewer under load, on loopback: dozens of clients connect, move their cameras and drop, some of them sending
malformed messages, while one client stays; a malformed message closes its own client alone, the staying client keeps
getting renders, and every dropped client's render loop is let go."""
from __future__ import annotations

import random
import threading
import time

import msgspec
import viser
import zstandard
from websockets.exceptions import ConnectionClosed
from websockets.sync.client import connect

from pipeline.viewer.server import Viewer, ViewOptions
from tests.pipeline.test_viewer import free_port, scene_out, wait_for  # noqa: F401 (scene_out is a fixture)

CLIENTS, MALFORMED_EVERY, SECONDS = 40, 5, 60.0
RENDER = "BackgroundImageMessage"


def message_types(raw: bytes) -> list[str]:
    """The types of the messages in one of viser's frames: two little-endian sizes, then zstd-compressed msgpack
    (read with msgspec, which viser itself uses: no package beyond the base install)."""
    decompressed, compressed = int.from_bytes(raw[:8], "little"), int.from_bytes(raw[8:16], "little")
    inner = zstandard.ZstdDecompressor().decompress(raw[16:16 + compressed], max_output_size=decompressed)
    return [m.get("type", "") for m in msgspec.msgpack.decode(inner).get("messages", [])]


def camera_message(rng: random.Random) -> bytes:
    position = [rng.uniform(-3, 3), rng.uniform(-3, 3), rng.uniform(1, 3)]
    return msgspec.msgpack.encode({"type": "ViewerCameraMessage", "wxyz": [1.0, 0.0, 0.0, 0.0], "position": position,
                          "fov": 0.9, "near": 0.01, "far": 100.0, "image_height": 480, "image_width": 640,
                          "look_at": [0.0, 0.0, 0.0], "up_direction": [0.0, 0.0, 1.0]})


MALFORMED = [b"\x00\xffnot msgpack at all", msgspec.msgpack.encode({"type": "NoSuchMessage", "x": 1}),
             msgspec.msgpack.encode({"type": "ViewerCameraMessage", "wxyz": "sideways"}), msgspec.msgpack.encode([1, 2, 3])]


def client(port: int):
    return connect(f"ws://127.0.0.1:{port}", subprotocols=[f"viser-v{viser.__version__}"], open_timeout=10,
                   max_size=None)


def received_render(ws, seconds: float) -> bool:
    deadline = time.monotonic() + seconds
    while time.monotonic() < deadline:
        try:
            message = ws.recv(timeout=max(deadline - time.monotonic(), 0.01))
        except TimeoutError:
            return False
        if isinstance(message, bytes) and RENDER in message_types(message):
            return True
    return False


def closed_by_server(ws, seconds: float) -> bool:
    deadline = time.monotonic() + seconds
    try:
        while time.monotonic() < deadline:
            ws.recv(timeout=max(deadline - time.monotonic(), 0.01))
    except ConnectionClosed:
        return True
    except TimeoutError:
        return False
    return False


def test_dozens_of_clients_come_and_go_and_a_malformed_message_closes_its_client_alone(scene_out):
    viewer = Viewer(scene_out, ViewOptions(port=free_port(), resolution=64, preview=32, settle=0.05))
    viewer.start()
    outcomes: dict[int, str] = {}
    try:
        steady = client(viewer.port)
        steady.send(camera_message(random.Random(0)))
        assert received_render(steady, 15), "the first client got no render"

        def visit(i: int) -> None:
            rng = random.Random(i)
            try:
                with client(viewer.port) as ws:
                    for _ in range(3):
                        ws.send(camera_message(rng))
                        time.sleep(rng.uniform(0, 0.1))
                    if i % MALFORMED_EVERY == 0:
                        ws.send(MALFORMED[(i // MALFORMED_EVERY) % len(MALFORMED)])
                        outcomes[i] = "closed" if closed_by_server(ws, 30) else "left open"
                    else:
                        outcomes[i] = "rendered" if received_render(ws, 30) else "no render"
                    if rng.random() < 0.5:
                        ws.socket.close()  # dropped without a goodbye, as a closed laptop lid
            except Exception as e:  # any failure to connect is this test's finding
                outcomes[i] = f"{type(e).__name__}: {e}"

        started = time.monotonic()
        visitors = [threading.Thread(target=visit, args=(i,), daemon=True) for i in range(CLIENTS)]
        for thread in visitors:
            thread.start()
            time.sleep(0.02)
        for thread in visitors:
            thread.join(timeout=max(SECONDS - (time.monotonic() - started), 0.1))
        assert all(not thread.is_alive() for thread in visitors), f"clients still busy after {SECONDS} s"

        malformed = {i for i in range(CLIENTS) if i % MALFORMED_EVERY == 0}
        assert {outcomes[i] for i in malformed} == {"closed"}, outcomes
        assert {outcomes[i] for i in set(range(CLIENTS)) - malformed} == {"rendered"}, outcomes

        steady.send(camera_message(random.Random(1)))
        assert received_render(steady, 15), "the client that stayed got no render after the others came and went"
        wait_for(lambda: len(viewer._loops) == 1, 10, "the dropped clients' render loops to be let go")
        steady.close()
    finally:
        viewer.stop()
