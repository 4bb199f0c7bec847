"""Logging for the service and the command line: the standard logging module with timestamps,
Warp's per-module load lines silenced, and a progress line while kernels compile on a first run."""

from __future__ import annotations

import contextlib
import logging
import os
import sys
import threading
import time
from pathlib import Path

__all__ = ["quiet_warp", "setup_logging", "watch_kernel_compiles"]

log = logging.getLogger("inhand_tracker")
_watching = False


class _Stderr(logging.StreamHandler):
    """A handler that writes to whatever ``sys.stderr`` is when it writes: a command run in-process
    (the tests, through typer's runner) swaps the stream per call."""

    @property
    def stream(self):
        return sys.stderr

    @stream.setter
    def stream(self, _value) -> None:
        pass


def setup_logging(level: str | int = "INFO") -> None:
    """Log to stderr with timestamps; ``level`` also from INHAND_LOG_LEVEL. Idempotent."""
    level = os.environ.get("INHAND_LOG_LEVEL", level)
    root = logging.getLogger()
    if not any(isinstance(h, _Stderr) for h in root.handlers):
        handler = _Stderr()
        handler.setFormatter(
            logging.Formatter("%(asctime)s %(levelname)-7s %(name)s: %(message)s", "%Y-%m-%d %H:%M:%S")
        )
        root.addHandler(handler)
    root.setLevel(level.upper() if isinstance(level, str) else level)
    logging.getLogger("matplotlib").setLevel(logging.WARNING)


def quiet_warp() -> None:
    """Silence Warp's banner (printed to stdout, where a command's JSON goes) and its "Module ...
    load on device" line per module (about 60 on a first start, before anything of ours); on a
    machine without NVIDIA's driver, also the "CUDA warning" its native library prints when it
    looks for one (a CPU is a supported device, not a fault)."""
    import warp as wp

    wp.config.log_level = wp.LOG_WARNING
    if not _cuda_driver():
        with _native_stderr_silenced():
            wp.init()


def _cuda_driver() -> bool:
    """Whether NVIDIA's driver library loads, as Warp looks for it."""
    import ctypes

    for name in ("libcuda.so", "libcuda.so.1", "nvcuda.dll"):
        try:
            ctypes.CDLL(name)
            return True
        except OSError:
            continue
    return False


@contextlib.contextmanager
def _native_stderr_silenced():
    """File descriptor 2 to /dev/null for a moment: a native library's fprintf does not go through
    Python's sys.stderr, so redirecting that would not reach it."""
    sys.stderr.flush()
    saved = os.dup(2)
    try:
        with open(os.devnull, "w") as null:
            os.dup2(null.fileno(), 2)
            yield
    finally:
        os.dup2(saved, 2)
        os.close(saved)


def watch_kernel_compiles(every_s: float = 5.0) -> None:
    """Log a progress line every ``every_s`` while new kernel modules appear in Warp's cache.

    Warp has no compile callback, and with its own lines silenced a cold first start would sit
    silent for a minute or more; the cache folder gains one entry per compiled module, so its
    count is the progress. A daemon thread: it costs a directory listing every few seconds.
    """
    global _watching
    if _watching:
        return
    _watching = True
    import warp as wp

    wp.init()
    cache = Path(wp.config.kernel_cache_dir)

    def count() -> int:
        try:
            return sum(1 for _ in cache.iterdir())
        except OSError:
            return 0

    def watch() -> None:
        start, seen = time.monotonic(), count()
        first = seen
        announced = False
        while True:
            time.sleep(every_s)
            now = count()
            if now > seen:
                if not announced:
                    log.info("compiling kernels on a first run; they are cached in %s for later starts", cache)
                    announced = True
                log.info("compiling kernels: %d modules built, %.0f s", now - first, time.monotonic() - start)
                seen = now

    threading.Thread(target=watch, name="inhand-compile-watch", daemon=True).start()
