"""What the ``larc`` command line shows on stderr and writes: log messages, progress bars, output
files and the time per phase.

Log messages of the loggers ``larc`` (the command line) and ``larc_jax`` (the library) go to
stderr as ``larc: ...`` lines (``--quiet``: errors only; ``-v``: debug lines too); progress
bars are tqdm bars on stderr, shown when stderr is a terminal (``--progress`` /
``--no-progress`` force), and log lines are written around them. Each helper takes the parsed
arguments (an ``argparse.Namespace``) and reads the flags it needs with defaults, so it serves
every subcommand.
"""

from __future__ import annotations

import contextlib
import logging
import sys
import time
import warnings

from ..errors import LarcInputError

__all__ = ["LogFormatter", "BarSafeHandler", "logging_for", "progress_bar", "write_output", "PhaseTimer"]

log = logging.getLogger("larc")


class LogFormatter(logging.Formatter):
    """``larc: message``; ``larc: warning: ...`` / ``larc: error: ...``; ``larc: debug [logger]: ...``."""

    def format(self, record: logging.LogRecord) -> str:
        msg = record.getMessage()
        if record.exc_info:
            msg += "\n" + self.formatException(record.exc_info)
        if record.levelno >= logging.WARNING:
            return f"larc: {record.levelname.lower()}: {msg}"
        if record.levelno < logging.INFO:
            return f"larc: debug [{record.name}]: {msg}"
        return f"larc: {msg}"


class BarSafeHandler(logging.StreamHandler):
    """Writes through ``tqdm.write``, which clears and redraws a progress bar being shown."""

    def emit(self, record: logging.LogRecord) -> None:
        try:
            from tqdm import tqdm

            tqdm.write(self.format(record), file=self.stream)
        except Exception:  # noqa: BLE001 - logging must never raise
            self.handleError(record)


@contextlib.contextmanager
def logging_for(args):
    """Route loggers ``larc`` (the command line) and ``larc_jax`` (the library modules), with
    their children, to stderr at the level the flags ask for; restore the previous
    configuration afterwards (``main`` may be called in-process, e.g. by tests)."""
    quiet, verbose = getattr(args, "quiet", False), getattr(args, "verbose", False)
    level = logging.ERROR if quiet else (logging.DEBUG if verbose else logging.INFO)
    ours = [logging.getLogger(name) for name in ("larc", "larc_jax")]
    jax_log = logging.getLogger("jax")
    saved = [(lg.level, lg.propagate, list(lg.handlers)) for lg in ours], jax_log.level
    handler = BarSafeHandler(sys.stderr)
    handler.setFormatter(LogFormatter())
    for lg in ours:
        lg.handlers = [handler]
        lg.setLevel(level)
        lg.propagate = False
    jax_log.setLevel(logging.ERROR if quiet else logging.WARNING)  # backend probing noise
    try:
        with warnings.catch_warnings():
            if quiet:
                warnings.simplefilter("ignore")
            yield
    finally:
        for lg, (lvl, prop, handlers) in zip(ours, saved[0]):
            lg.setLevel(lvl)
            lg.propagate = prop
            lg.handlers = handlers
        jax_log.setLevel(saved[1])


def progress_bar(args, **kwargs):
    """A tqdm bar on stderr: shown if ``--progress``, hidden if ``--quiet`` or ``--no-progress``,
    else shown when stderr is a terminal (after half a second, so quick steps stay silent)."""
    from tqdm import tqdm

    forced = getattr(args, "progress", None)
    show = not getattr(args, "quiet", False) and (forced if forced is not None else sys.stderr.isatty())
    return tqdm(file=sys.stderr, disable=not show, delay=0.0 if forced else 0.5, leave=False,
                dynamic_ncols=True, **kwargs)


def write_output(path, data: bytes, what: str) -> None:
    """Write an output file atomically; a write failure is a usage error (exit 2)."""
    from ..io import atomic_write_bytes

    try:
        atomic_write_bytes(path, data)
    except OSError as exc:
        raise LarcInputError(f"{path}: cannot write {what} ({exc.strerror or exc})") from None
    log.info("wrote %s (%s)", path, what)


class PhaseTimer:
    """Seconds per phase of a command, for the ``-v`` log."""

    def __init__(self):
        self.t = time.perf_counter()
        self.laps: dict[str, float] = {}

    def lap(self, name: str) -> None:
        now = time.perf_counter()
        self.laps[name] = now - self.t
        self.t = now

    def log(self, result) -> None:
        log.debug("time: %s (of which compiling %.2f s, running %.2f s)",
                  ", ".join(f"{k} {v:.2f} s" for k, v in self.laps.items()), result.compile_time_s,
                  result.wall_time_s - result.compile_time_s)
