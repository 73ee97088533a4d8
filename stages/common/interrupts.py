"""Ctrl-C as a request: long work stops at a point of its choosing and keeps what it has made."""
from __future__ import annotations

import signal
import threading


class StopRequest:
    """Within `with StopRequest() as stop:` the first Ctrl-C sets `stop.requested` (the work checks it
    and stops when it can); the second raises KeyboardInterrupt. Only the main thread can take signals;
    elsewhere Ctrl-C simply raises."""

    def __init__(self):
        self.requested = False
        self._previous = None

    def __enter__(self):
        if threading.current_thread() is threading.main_thread():
            self._previous = signal.signal(signal.SIGINT, self._handle)
        return self

    def _handle(self, signum, frame):
        self.requested = True
        signal.signal(signal.SIGINT, signal.default_int_handler)

    def __exit__(self, *exc):
        if self._previous is not None:
            signal.signal(signal.SIGINT, self._previous)
        return False
