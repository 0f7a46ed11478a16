"""File input/output shared by the library and the drivers: atomic writes, and the guarded
reading of user files (text, YAML, JSON) that turns every way a file can be bad into one
:class:`~larc_jax.errors.LarcInputError` line naming the file.

It also holds the parsers of numbers and vectors that every reader shares
(:func:`parse_number`, :func:`parse_vector`) and the array check of the Python API's records
(:func:`real_array`), and the SHA-256 of user files (:func:`file_sha256`, :func:`current_sha256`).
Trajectory and scene readers live in :mod:`larc_jax.model.trajectory` and :mod:`larc_jax.model.scene`.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import logging
import os
import reprlib
import stat
import tempfile
import threading
from pathlib import Path

import numpy as np
import yaml

from .errors import LarcInputError
from .plain_yaml import plain_documents

__all__ = [
    "atomic_write_text", "atomic_write_bytes", "atomic_write_json",
    "read_input_bytes", "read_input_text", "decode_text", "check_keys", "parse_yaml_documents", "parse_yaml", "parse_json", "short_repr",
    "deferred_log", "parse_number", "parse_vector", "real_array", "MAX_INPUT_BYTES", "MAX_NESTING",
    "file_sha256", "current_sha256", "UNSETTLED_NS",
]

MAX_INPUT_BYTES = 512 * 2**20
"""Input files larger than this (512 MiB) are refused; at most this many bytes (and one more) are
read, whatever the file's size says (:func:`read_input_bytes`)."""
MAX_NESTING = 64
"""YAML and JSON documents nested deeper than this (lists and mappings) are refused: no input
format nests beyond about 8, and the readers and checkers then never recurse deeply."""


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


def read_input_bytes(path: str | os.PathLike, what: str = "file", cap: int | None = None) -> bytes:
    """The bytes of a user file, at most ``cap`` (default :data:`MAX_INPUT_BYTES`), or
    :class:`LarcInputError` ``"<path>: <problem>"``.

    The file is opened once (without blocking, so a FIFO with no writer cannot hang it) and must
    be a regular file by ``fstat`` of that open file: a directory, FIFO, socket or device (a
    link to ``/dev/zero``) is refused. ``st_size`` is not trusted: at most ``cap + 1`` bytes are
    read, and a file that has more (it grew while read) is refused.
    """
    path = Path(path)
    cap = MAX_INPUT_BYTES if cap is None else cap
    try:
        fd = os.open(path, os.O_RDONLY | getattr(os, "O_NONBLOCK", 0) | getattr(os, "O_CLOEXEC", 0))
    except FileNotFoundError:
        raise LarcInputError(f"{path}: {what} does not exist") from None
    except IsADirectoryError:
        raise LarcInputError(f"{path}: is a directory, expected a {what}") from None
    except PermissionError:
        raise LarcInputError(f"{path}: cannot read {what}: permission denied") from None
    except OSError as exc:
        raise LarcInputError(f"{path}: cannot read {what} ({exc.strerror or exc})") from None
    try:
        mode = os.fstat(fd).st_mode
        if stat.S_ISDIR(mode):
            raise LarcInputError(f"{path}: is a directory, expected a {what}")
        if not stat.S_ISREG(mode):
            kind = ("a FIFO (named pipe)" if stat.S_ISFIFO(mode) else "a device" if stat.S_ISCHR(mode) or
                    stat.S_ISBLK(mode) else "a socket" if stat.S_ISSOCK(mode) else "not a regular file")
            raise LarcInputError(f"{path}: {what} is {kind}; expected a regular file")
        chunks, total = [], 0
        while total <= cap:
            block = os.read(fd, min(1 << 20, cap + 1 - total))
            if not block:
                break
            chunks.append(block)
            total += len(block)
    except OSError as exc:
        raise LarcInputError(f"{path}: cannot read {what} ({exc.strerror or exc})") from None
    finally:
        os.close(fd)
    if total > cap:
        raise LarcInputError(f"{path}: {what} is larger than the {cap / 2**20:.0f} MiB limit for input files")
    return b"".join(chunks)


def read_input_text(path: str | os.PathLike, what: str = "file") -> str:
    """The UTF-8 text of a user file, or :class:`LarcInputError` ``"<path>: <problem>"``.

    Problems: those of :func:`read_input_bytes` (missing, a directory or other non-regular
    file, unreadable, larger than :data:`MAX_INPUT_BYTES`), and not UTF-8 text (binary). A
    UTF-8 byte-order mark is dropped. ``what`` names the file's role in the messages ("scene
    file", "robot file", ...).
    """
    return decode_text(read_input_bytes(path, what), path)


def decode_text(data: bytes, path: str | os.PathLike) -> str:
    """``data`` (the bytes of ``path``, read once: a reader that also hashes them hashes what it
    parsed) as UTF-8 text, a byte-order mark dropped; :class:`LarcInputError` if it is not."""
    try:
        return data.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        raise LarcInputError(
            f"{path}: not a text file (byte {exc.start} is not UTF-8; expected YAML/JSON text)"
        ) from None


def check_keys(mapping, allowed, source: str, where: str = "", ignored=(), kind: str = "field") -> None:
    """Refuse a key of ``mapping`` that is neither ``allowed`` nor documented as ``ignored``:
    :class:`LarcInputError` ``"<source>: <where>: unknown field '<key>' (expected one of ...)"``.

    Every reader calls it on every mapping it reads, so a typo (``obstacle:`` for ``boxes:``)
    is an error rather than a field silently left out. ``kind`` names what a key is ("column").
    """
    known = set(allowed) | set(ignored)
    for key in mapping:
        if key not in known:
            at = f"{where}: " if where else ""
            raise LarcInputError(f"{source}: {at}unknown {kind} {short_repr(key)} (expected "
                                 f"{', '.join(sorted(map(str, allowed)))})")


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


class _UniqueKeys(yaml.constructor.SafeConstructor):
    """SafeConstructor that refuses a mapping holding the same key twice (PyYAML keeps the
    last one silently, so ``{boxes: [...], boxes: []}`` would read as an empty scene)."""

    def construct_mapping(self, node, deep=False):
        if isinstance(node, yaml.MappingNode):
            seen = set()
            for key_node, _ in node.value:
                if key_node.tag == "tag:yaml.org,2002:merge":
                    continue  # '<<': merged keys may be overridden, as YAML says
                key = self.construct_object(key_node, deep=True)
                try:
                    duplicate = key in seen
                    seen.add(key)
                except TypeError:  # an unhashable key: SafeConstructor reports it
                    continue
                if duplicate:
                    raise yaml.constructor.ConstructorError(
                        None, None, f"found duplicate key {short_repr(key)}", key_node.start_mark)
        return super().construct_mapping(node, deep)


try:  # libyaml's scanner and parser (fast), PyYAML's composer and constructor (recursion-checked)
    from yaml._yaml import CParser as _CParser

    class SafeYamlLoader(yaml.composer.Composer, _UniqueKeys, yaml.resolver.Resolver, _CParser):
        """Safe YAML loader: libyaml parses, pure Python composes and constructs.

        ``yaml.CSafeLoader`` composes in C without a depth check, so a deeply nested document
        (``[[[[...``) overflows the C stack and kills the process; the Python composer raises
        ``RecursionError`` instead, which is reported as bad input. Duplicate keys are refused.
        """

        def __init__(self, stream):
            _CParser.__init__(self, stream)
            _UniqueKeys.__init__(self)
            yaml.resolver.Resolver.__init__(self)
            yaml.composer.Composer.__init__(self)
except ImportError:  # pragma: no cover - PyYAML without libyaml
    class SafeYamlLoader(yaml.reader.Reader, yaml.scanner.Scanner, yaml.parser.Parser,  # type: ignore[no-redef]
                         yaml.composer.Composer, _UniqueKeys, yaml.resolver.Resolver):
        def __init__(self, stream):
            yaml.reader.Reader.__init__(self, stream)
            yaml.scanner.Scanner.__init__(self)
            yaml.parser.Parser.__init__(self)
            yaml.composer.Composer.__init__(self)
            _UniqueKeys.__init__(self)
            yaml.resolver.Resolver.__init__(self)


def _check_shape(doc, source: str, limit: int) -> None:
    """Refuse a document nested deeper than :data:`MAX_NESTING`, one that contains itself (YAML
    ``&a [*a]``), or one whose aliases expand it to more than ``limit`` values (``billion
    laughs``): readers walk documents as trees. Iterative, and each shared value is counted once
    per visit from its memo, so the check itself is linear in the document's text."""
    memo: dict[int, tuple[int, int]] = {}   # id -> (nesting depth, values in its expansion)
    open_ids: set[int] = set()              # started, not finished: the current path
    stack = [(doc, False)]
    while stack:
        obj, done = stack.pop()
        if not isinstance(obj, (list, dict)):
            continue  # a scalar document
        children = list(obj.values()) if isinstance(obj, dict) else obj
        if done:
            depth, count = 0, 1
            for c in children:
                d, n = memo.get(id(c), (0, 1)) if isinstance(c, (list, dict)) else (0, 1)
                depth, count = max(depth, d), count + n
            if depth + 1 > MAX_NESTING:
                raise LarcInputError(f"{source}: nested more than {MAX_NESTING} levels deep")
            if count > limit:
                raise LarcInputError(f"{source}: its aliases expand it to more than {limit} values")
            memo[id(obj)] = (depth + 1, count)
            open_ids.discard(id(obj))
            continue
        if id(obj) in memo:
            continue
        if len(open_ids) >= MAX_NESTING:
            raise LarcInputError(f"{source}: nested more than {MAX_NESTING} levels deep")
        open_ids.add(id(obj))
        stack.append((obj, True))
        for c in children:
            if isinstance(c, (list, dict)) and id(c) not in memo:
                if id(c) in open_ids:
                    raise LarcInputError(f"{source}: a YAML alias makes the document contain itself")
                stack.append((c, False))


def parse_yaml_documents(text: str, source: str) -> list:
    """All documents of a YAML text (safe types only); :class:`LarcInputError` if it is not YAML,
    holds a duplicate key, or is nested or aliased beyond the limits of :func:`_check_shape`.

    A plain stream (no anchors, aliases or explicit tags: what planners write) is built straight
    from the parser's events (:func:`larc_jax.plain_yaml.plain_documents`: the parse alone 2.2-2.5x
    faster, the same documents); anything else, and every error, goes through the full loader."""
    limit = len(text) + 1000
    docs = plain_documents(text, SafeYamlLoader, MAX_NESTING, limit)
    if docs is not None:
        return docs
    try:
        docs = list(yaml.load_all(text, Loader=SafeYamlLoader))
    except yaml.YAMLError as exc:  # libyaml >= 0.2.5 stops at 1000 levels itself
        deep = "nested too deeply: " if "maximum nesting depth" in str(exc) else ""
        raise LarcInputError(f"{source}: not valid YAML ({deep}{_one_line(exc)})") from None
    except RecursionError:
        raise LarcInputError(f"{source}: not valid YAML (nested too deeply)") from None
    except (ValueError, OverflowError) as exc:  # e.g. a 5000-digit integer, a bad timestamp
        raise LarcInputError(f"{source}: not valid YAML ({_one_line(exc)})") from None
    for doc in docs:
        _check_shape(doc, source, limit)
    return docs


def parse_yaml(text: str, source: str):
    """The single document of a YAML text (``None`` when empty)."""
    docs = parse_yaml_documents(text, source)
    if len(docs) > 1:
        raise LarcInputError(f"{source}: holds {len(docs)} YAML documents separated by '---'; expected one")
    return docs[0] if docs else None


def _unique_pairs(pairs: list) -> dict:
    out = dict(pairs)
    if len(out) != len(pairs):
        seen: set = set()
        key = next(k for k, _ in pairs if k in seen or seen.add(k))
        raise _DuplicateKey(key)
    return out


class _DuplicateKey(Exception):
    pass


def parse_json(text: str, source: str):
    """A JSON document (``NaN``/``Infinity`` literals accepted, checked later by the readers);
    :class:`LarcInputError` if it is not JSON, repeats a key in an object (Python would keep the
    last silently), or nests deeper than :data:`MAX_NESTING`."""
    try:
        doc = json.loads(text, object_pairs_hook=_unique_pairs)
    except _DuplicateKey as exc:
        raise LarcInputError(f"{source}: not valid JSON (an object holds the key {short_repr(exc.args[0])} "
                             "twice)") from None
    except RecursionError:
        raise LarcInputError(f"{source}: not valid JSON (nested too deeply)") from None
    except json.JSONDecodeError as exc:
        raise LarcInputError(f"{source}: not valid JSON ({exc.msg}, line {exc.lineno} column {exc.colno})") from None
    except ValueError as exc:  # an integer with too many digits
        raise LarcInputError(f"{source}: not valid JSON ({_one_line(exc)})") from None
    _check_shape(doc, source, len(text) + 1000)
    return doc


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
    if all(type(v) is float or type(v) is int for v in value):  # the common case, at C speed (not bool)
        try:
            out = np.array(value, dtype=np.float64)
        except OverflowError:  # an int too large for a float: the loop below names it
            out = None
        if out is not None and (not finite or np.isfinite(out).all()):
            return out
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


def file_sha256(path: str | os.PathLike, what: str = "file") -> str:
    """SHA-256 of a file's bytes, read as every user file is (:func:`~larc_jax.io.read_input_bytes`:
    a regular file, at most the input cap; else :class:`LarcInputError` naming it as ``what``)."""
    return hashlib.sha256(read_input_bytes(path, what)).hexdigest()


UNSETTLED_NS = 2_000_000_000
"""A file changed less than this long (2 s) before it was hashed is hashed again on the next
call (:func:`current_sha256`)."""
_CURRENT: dict[str, tuple[tuple, str]] = {}


def current_sha256(path: str | os.PathLike, what: str = "file") -> str:
    """:func:`file_sha256` of the file as it is now, recomputed only when its status changed:
    the hot paths that check, on every ``certify`` call, that the robot's files are still those
    it was built from (the URDF, and the meshes the hull parts came from: 9 MB, 7 ms a call on
    PIPER) hash a file again only when its device, inode, size, modification or *change* time
    differ from the hash's.

    Why this sees every change of content. Writing to a file, replacing it or setting its
    times (``touch``, ``os.utime``) sets its change time (ctime) to the kernel's clock, which a
    user cannot set. The status is taken before the bytes are read, at time ``S``; any later
    write gets a ctime of at least ``S`` less the clock's tick (milliseconds), so a different
    status, as long as the file's previous ctime was more than :data:`UNSETTLED_NS` before
    ``S``: a hash is remembered only then (git's "racily clean" rule), and only for a regular
    file. The assumption is a system clock that does not step back by 2 s between two calls;
    ``larc verify`` and the certificate's own hashes never use this (:func:`file_sha256`)."""
    import time

    key_path = os.fspath(path)
    try:
        st = os.stat(key_path)
    except OSError:
        st = None
    status = None if st is None or not stat.S_ISREG(st.st_mode) else (
        st.st_dev, st.st_ino, st.st_size, st.st_mtime_ns, st.st_ctime_ns)
    hit = _CURRENT.get(key_path)
    if status is not None and hit is not None and hit[0] == status:
        return hit[1]
    now_ns = time.time_ns()
    digest = file_sha256(path, what)
    if status is not None and now_ns - max(st.st_ctime_ns, st.st_mtime_ns) > UNSETTLED_NS:
        if len(_CURRENT) > 4096:
            _CURRENT.clear()
        _CURRENT[key_path] = (status, digest)
    return digest
