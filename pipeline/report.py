"""What a person sees while the pipeline runs: progress bars with an ETA, warnings, one summary line per stage.

On a terminal a bar redraws itself in place; anywhere else (a log file, CI, a batch worker's log) progress is a plain
line every PLAIN_SECONDS, so a log reads as lines rather than carriage-return redraws run together.
"""
from __future__ import annotations

import sys
from collections.abc import Iterable, Iterator
from typing import TypeVar

from tqdm import tqdm

T = TypeVar("T")
# Seconds between the plain progress lines of output that is not a terminal: three a minute.
PLAIN_SECONDS = 20.0
PLAIN_FORMAT = "{desc}: {n_fmt}/{total_fmt} ({percentage:.0f}%), {elapsed} elapsed, ETA {remaining}{postfix}"
PLAIN_COUNT = "{desc}: {n_fmt}, {elapsed} elapsed{postfix}"  # when the total is not known


class LogLines(tqdm):
    """A tqdm bar whose every display is a line of its own, for output that is not a terminal."""

    def display(self, msg: str | None = None, pos: int | None = None) -> bool:
        if msg == "":  # closing clears a redrawn bar; a line in a log stays
            return False
        self.fp.write((self.__str__() if msg is None else msg).rstrip() + "\n")
        self.fp.flush()
        return True


# A list of names in a message shows this many, then says how many more.



class Reporter:
    """Prints to stderr (progress, warnings) and stdout (stage summary lines).

    `quiet` hides progress and info but never warnings or summaries, so scripts still see what happened. `plain`
    makes progress plain lines every PLAIN_SECONDS (default: when stderr is not a terminal).
    """

    def __init__(self, quiet: bool = False, plain: bool | None = None):
        self.quiet = quiet
        self.plain = plain

    def info(self, message: str) -> None:
        if not self.quiet:
            print(f"  {message}", file=sys.stderr, flush=True)

    def warn(self, message: str) -> None:
        print(f"  warning: {message}", file=sys.stderr, flush=True)

    def summary(self, stage: str, line: str) -> None:
        print(f"[{stage}] {line}", flush=True)

    def bar(self, iterable: Iterable[T] | None = None, total: int | None = None, desc: str = "") -> tqdm:
        """A tqdm bar (iterate it, or call .update/.set_postfix); silent when quiet, plain lines when `plain`."""
        if self.plain if self.plain is not None else not sys.stderr.isatty():
            known = total is not None or hasattr(iterable, "__len__")
            return LogLines(iterable, total=total, desc=f"  {desc}", disable=self.quiet, leave=False, file=sys.stderr,
                            mininterval=PLAIN_SECONDS, maxinterval=PLAIN_SECONDS, delay=PLAIN_SECONDS,
                            bar_format=PLAIN_FORMAT if known else PLAIN_COUNT)
        return tqdm(iterable, total=total, desc=f"  {desc}", disable=self.quiet, leave=False,
                    file=sys.stderr, dynamic_ncols=True, mininterval=0.5)

    def track(self, iterable: Iterable[T], total: int | None = None, desc: str = "") -> Iterator[T]:
        yield from self.bar(iterable, total=total, desc=desc)
