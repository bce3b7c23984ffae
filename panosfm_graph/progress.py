"""The one progress helper: a tqdm bar on stderr when it is a terminal, quiet otherwise."""
from __future__ import annotations

import logging
import sys
import time
from contextlib import contextmanager
from typing import Iterable, Iterator, TypeVar

T = TypeVar("T")
log = logging.getLogger("panosfm")

_enabled = True


def set_enabled(flag: bool) -> None:
    global _enabled
    _enabled = flag


def progress(items: Iterable[T], desc: str, total: int | None = None) -> Iterator[T]:
    """Yields ``items``, showing a progress bar labelled ``desc`` on an interactive stderr."""
    if _enabled and sys.stderr.isatty():
        from tqdm import tqdm

        yield from tqdm(items, desc=desc, total=total, leave=False, dynamic_ncols=True)
    else:
        yield from items


@contextmanager
def stage(name: str, timings: dict[str, float] | None = None) -> Iterator[None]:
    """Times a pipeline stage, logs it, and records seconds in ``timings[name]``."""
    log.info("%s ...", name)
    t0 = time.perf_counter()
    yield
    dt = time.perf_counter() - t0
    if timings is not None:
        timings[name] = timings.get(name, 0.0) + dt
    log.info("%s done in %.2f s", name, dt)
