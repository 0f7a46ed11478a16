"""File input/output shared by the library and the drivers: atomic writes, and the guarded
reading of user files (text, YAML, JSON) that turns every way a file can be bad into one
:class:`~larc_jax.errors.LarcInputError` line naming the file.

It also holds the parsers of numbers and vectors that every reader shares
(:func:`parse_number`, :func:`parse_vector`) and the array check of the Python API's records
(:func:`real_array`). Trajectory and scene readers live in :mod:`larc_jax.trajectory` and :mod:`larc_jax.scene`.
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import reprlib
import tempfile
import threading
from pathlib import Path

import numpy as np
import yaml

from .errors import LarcInputError

__all__ = [
    "atomic_write_text", "atomic_write_bytes", "atomic_write_json",
    "read_input_text", "parse_yaml_documents", "parse_yaml", "parse_json", "short_repr",
    "deferred_log", "parse_number", "parse_vector", "real_array", "MAX_INPUT_BYTES",
]

MAX_INPUT_BYTES = 512 * 2**20
"""Input files larger than this (512 MiB) are refused before they are read."""


def atomic_write_bytes(path: str | os.PathLike, data: bytes) -> None:
    """Write ``data`` to ``path`` so that readers see the old file or the new one, never a part.

    The bytes go to a temporary file in the same folder, are flushed to disk, then renamed over
    the target (``os.replace`` is atomic on POSIX). A killed writer leaves at most a stray
    ``.tmp`` file, which is removed on error.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        # mkstemp creates 0600; give the result the permissions a plain open() would.
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o666 & ~umask)
        with os.fdopen(fd, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        try:
            os.unlink(tmp)
        except FileNotFoundError:
            pass
        raise


def atomic_write_text(path: str | os.PathLike, text: str) -> None:
    atomic_write_bytes(path, text.encode("utf-8"))


def atomic_write_json(path: str | os.PathLike, obj) -> None:
    atomic_write_text(path, json.dumps(obj, indent=2, sort_keys=False) + "\n")


# ----------------------------------------------------------------------------------------------
# Reading user files
# ----------------------------------------------------------------------------------------------

_short = reprlib.Repr()
_short.maxstring = _short.maxother = 60
_short.maxlist = _short.maxtuple = _short.maxdict = 8
_short.maxlevel = 2


def short_repr(value, limit: int = 100) -> str:
    """``repr`` cut to about ``limit`` characters (error messages stay one readable line)."""
    text = _short.repr(value)
    return text if len(text) <= limit else text[: limit - 3] + "..."


def read_input_text(path: str | os.PathLike, what: str = "file") -> str:
    """The UTF-8 text of a user file, or :class:`LarcInputError` ``"<path>: <problem>"``.

    Problems: missing, a directory, unreadable (permissions, I/O), larger than
    :data:`MAX_INPUT_BYTES`, not UTF-8 text (binary). A UTF-8 byte-order mark is dropped.
    ``what`` names the file's role in the messages ("scene file", "robot file", ...).
    """
    path = Path(path)
    try:
        size = path.stat().st_size
        if path.is_dir():
            raise IsADirectoryError
        if size > MAX_INPUT_BYTES:
            raise LarcInputError(
                f"{path}: {what} is {size / 2**20:.0f} MiB, larger than the "
                f"{MAX_INPUT_BYTES // 2**20} MiB limit for input files"
            )
        data = path.read_bytes()
    except FileNotFoundError:
        raise LarcInputError(f"{path}: {what} does not exist") from None
    except IsADirectoryError:
        raise LarcInputError(f"{path}: is a directory, expected a {what}") from None
    except PermissionError:
        raise LarcInputError(f"{path}: cannot read {what}: permission denied") from None
    except OSError as exc:
        raise LarcInputError(f"{path}: cannot read {what} ({exc.strerror or exc})") from None
    try:
        return data.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        raise LarcInputError(
            f"{path}: not a text file (byte {exc.start} is not UTF-8; expected YAML/JSON text)"
        ) from None


@contextlib.contextmanager
def deferred_log(logger: logging.Logger):
    """Hold ``logger``'s records while a file is read; emit them only if reading succeeds.

    A refused file then gives its one error line and nothing else (no "ignoring ..." warning
    about a file that was not used after all).
    """
    held: list[logging.LogRecord] = []
    thread = threading.get_ident()

    def hold(record: logging.LogRecord) -> bool:
        if record.thread != thread:  # another thread's record: not ours to hold
            return True
        held.append(record)
        return False

    logger.addFilter(hold)
    try:
        yield
    finally:
        logger.removeFilter(hold)
    for record in held:  # reached only without an exception
        logger.handle(record)


def _one_line(exc: BaseException) -> str:
    return " ".join(str(exc).split())


try:  # libyaml's scanner and parser (fast), PyYAML's composer and constructor (recursion-checked)
    from yaml._yaml import CParser as _CParser

    class SafeYamlLoader(yaml.composer.Composer, yaml.constructor.SafeConstructor,
                         yaml.resolver.Resolver, _CParser):
        """Safe YAML loader: libyaml parses, pure Python composes and constructs.

        ``yaml.CSafeLoader`` composes in C without a depth check, so a deeply nested document
        (``[[[[...``) overflows the C stack and kills the process; the Python composer raises
        ``RecursionError`` instead, which is reported as bad input.
        """

        def __init__(self, stream):
            _CParser.__init__(self, stream)
            yaml.constructor.SafeConstructor.__init__(self)
            yaml.resolver.Resolver.__init__(self)
            yaml.composer.Composer.__init__(self)
except ImportError:  # pragma: no cover - PyYAML without libyaml
    SafeYamlLoader = yaml.SafeLoader  # type: ignore[misc,assignment]


def parse_yaml_documents(text: str, source: str) -> list:
    """All documents of a YAML text (safe types only); :class:`LarcInputError` if it is not YAML."""
    try:
        return list(yaml.load_all(text, Loader=SafeYamlLoader))
    except yaml.YAMLError as exc:
        raise LarcInputError(f"{source}: not valid YAML ({_one_line(exc)})") from None
    except RecursionError:
        raise LarcInputError(f"{source}: not valid YAML (nested too deeply)") from None
    except (ValueError, OverflowError) as exc:  # e.g. a 5000-digit integer, a bad timestamp
        raise LarcInputError(f"{source}: not valid YAML ({_one_line(exc)})") from None


def parse_yaml(text: str, source: str):
    """The single document of a YAML text (``None`` when empty)."""
    docs = parse_yaml_documents(text, source)
    if len(docs) > 1:
        raise LarcInputError(f"{source}: holds {len(docs)} YAML documents separated by '---'; expected one")
    return docs[0] if docs else None


def parse_json(text: str, source: str):
    """A JSON document (``NaN``/``Infinity`` literals accepted, checked later by the readers)."""
    try:
        return json.loads(text)
    except RecursionError:
        raise LarcInputError(f"{source}: not valid JSON (nested too deeply)") from None
    except ValueError as exc:  # JSONDecodeError, or an integer with too many digits
        raise LarcInputError(f"{source}: not valid JSON ({_one_line(exc)})") from None


# ----------------------------------------------------------------------------------------------
# Numbers and vectors in parsed documents (one parser for every reader)
# ----------------------------------------------------------------------------------------------


def parse_number(value, source: str, where: str, *, finite: bool = False) -> float:
    """A YAML/JSON number as a float; :class:`LarcInputError` ``"<source>: <where> ..."`` for a
    bool, a string, ``None``, a container or an integer too large for a float (and for NaN or
    infinity when ``finite``)."""
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise LarcInputError(f"{source}: {where} is not a number ({short_repr(value)})")
    try:
        out = float(value)
    except OverflowError:
        raise LarcInputError(f"{source}: {where} is too large ({short_repr(value)})") from None
    if finite and not np.isfinite(out):
        raise LarcInputError(f"{source}: {where} must be finite, got {value!r}")
    return out


def parse_vector(value, n: int, source: str, where: str, *, finite: bool = False,
                 entries: str = "") -> np.ndarray:
    """A list of exactly ``n`` numbers as a float64 array (each entry as :func:`parse_number`).

    ``entries`` says what the entries are, for the wrong-length message (e.g. "one per
    joint_names entry").
    """
    if not isinstance(value, (list, tuple)):
        raise LarcInputError(f"{source}: {where} must be a list of {n} numbers, got {short_repr(value)}")
    if len(value) != n:
        raise LarcInputError(
            f"{source}: {where} has {len(value)} entries, expected {n}" + (f" ({entries})" if entries else ""))
    return np.array([parse_number(v, source, f"{where}[{i}]", finite=finite) for i, v in enumerate(value)],
                    dtype=np.float64).reshape(n)


def real_array(value, where: str, ndim: int, last: int | None = None) -> np.ndarray:
    """An array-like of real numbers (a NumPy or JAX array, nested lists) as a *read-only*
    float64 copy with ``ndim`` dimensions (and ``last`` entries along the last one, if given);
    :class:`LarcInputError` naming ``where`` otherwise. Used by the Python API's records
    (``Trajectory``, ``Scene``) so that bad input never fails deep inside NumPy or JAX."""
    try:
        raw = np.asarray(value)
    except (TypeError, ValueError) as exc:  # ragged nested lists, unconvertible objects
        raise LarcInputError(f"{where} must be an array of numbers ({_one_line(exc)})") from None
    if isinstance(value, (list, tuple)) and raw.dtype.kind in "iu" and any(
            isinstance(x, (bool, np.bool_)) for x in np.asarray(value, dtype=object).reshape(-1)):
        raise LarcInputError(f"{where} must be an array of real numbers, got a boolean in "
                             f"{' '.join(short_repr(value).split())}")
    if raw.dtype.kind not in "iuf" or (raw.dtype.kind == "f" and raw.dtype.itemsize > 8):
        got = (f"an array of dtype {raw.dtype}" if hasattr(value, "dtype")
               else f"{' '.join(short_repr(value).split())} (dtype {raw.dtype})")
        raise LarcInputError(f"{where} must be an array of real numbers (float64 or narrower), got {got}")
    if raw.ndim != ndim or (last is not None and raw.shape[-1] != last):
        want = "(" + ", ".join(["N"] * (ndim - 1) + [str(last) if last is not None else "N"]) + ")"
        raise LarcInputError(f"{where} must have shape {want}, got shape {raw.shape}")
    with np.errstate(over="ignore"):
        out = np.array(raw, dtype=np.float64)
    if raw.dtype.kind in "iu" and not np.array_equal(out.astype(raw.dtype), raw):
        raise LarcInputError(f"{where} holds integers that are not exactly representable as floats")
    out.flags.writeable = False
    return out
