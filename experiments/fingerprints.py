"""Fingerprints of a stage's inputs: data files, parameters, and the code that runs it.

A stage of :mod:`experiments.stageB` is up to date when the SHA-256 of everything its outputs
depend on is the one recorded when they were written. "Everything" is:

* its **data** files (trajectories, scenes, the capsule file, the URDF and its meshes, ...), by
  content and by their path relative to the repository;
* its **parameters** (the protocol values it reads), as JSON;
* its **code**: the *import closure* of the module that implements the stage
  (:func:`code_closure`), i.e. that module, every module of ``larc_jax`` or ``experiments``
  it imports (anywhere in the file, function-local imports included), and so on. Each file is
  hashed in a normalised form — parsed, docstrings removed, unparsed (:func:`normalised_source`)
  — so editing a comment or a docstring does not invalidate a result, but any change to what
  the code does does. A package's ``__init__.py`` counts only when a module imports a name *from
  the package itself* (``from larc_jax.enclosure import x``); importing a submodule
  (``from larc_jax.enclosure.meshes import x``) depends on that submodule, not on the
  re-exports beside it. Third-party packages are not hashed (their versions are recorded in
  the stage manifests, see :func:`environment`).

The closure over-approximates what a stage runs (a module is counted even if the stage calls
only one of its functions): a change can rerun a stage needlessly, never leave it stale.
"""

from __future__ import annotations

import ast
import functools
import hashlib
import inspect
import json
import textwrap
from pathlib import Path
from typing import Iterable, Sequence

ROOT = Path(__file__).resolve().parent.parent
OWN_PACKAGES = ("larc_jax", "experiments")
"""Top-level packages whose source is part of a code fingerprint."""
NOT_CODE = ("experiments.fingerprints",)
"""Modules never counted in a closure: this one computes the hashes, it does not produce results
(changing how it hashes changes every fingerprint anyway)."""

__all__ = ["sha_file", "fingerprint", "code_closure", "code_fingerprint", "module_imports", "normalised_source",
           "source_fingerprint", "environment"]


def sha_file(path: str | Path) -> str:
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


def _display_name(path: Path) -> str:
    try:
        return str(path.resolve().relative_to(ROOT))
    except ValueError:
        return path.name


def fingerprint(files: Iterable[str | Path], params: dict | None = None, code: Sequence[str] = ()) -> str:
    """SHA-256 over the contents of ``files`` (named by their path relative to the repository,
    else by file name), the JSON of ``params``, and the normalised code of the import closure of
    the modules ``code`` (dotted names, e.g. ``"experiments.audit"``)."""
    h = hashlib.sha256()
    for f in sorted({Path(x) for x in files}, key=_display_name):
        h.update(_display_name(f).encode() + b"\0")
        h.update(sha_file(f).encode() if f.is_file() else b"<missing>")
    h.update(json.dumps(params or {}, sort_keys=True, default=str).encode())
    if code:
        h.update(code_fingerprint(code).encode())
    return h.hexdigest()


# ----------------------------------------------------------------------------------------------
# Code
# ----------------------------------------------------------------------------------------------


def module_path(name: str) -> Path | None:
    """Source file of one of our modules (``a.b.c`` → ``a/b/c.py`` or ``a/b/c/__init__.py``)."""
    if name.split(".")[0] not in OWN_PACKAGES:
        return None
    base = ROOT.joinpath(*name.split("."))
    for p in (base.with_suffix(".py"), base / "__init__.py"):
        if p.is_file():
            return p
    return None


def _strip_docstrings(tree: ast.AST) -> ast.AST:
    """Drop every statement that is a bare string (docstrings of modules, classes, functions
    and attributes): it has no effect when the code runs."""
    for node in ast.walk(tree):
        for field in ("body", "orelse", "finalbody"):
            stmts = getattr(node, field, None)
            if isinstance(stmts, list):
                kept = [s for s in stmts if not (isinstance(s, ast.Expr) and isinstance(s.value, ast.Constant)
                                                  and isinstance(s.value.value, str))]
                if len(kept) != len(stmts):
                    setattr(node, field, kept or [ast.Pass()])
    return tree


def _normalised(text: str, filename: str = "<unknown>") -> str:
    """Python source without comments, docstrings or formatting (``ast.unparse`` of the
    docstring-free tree)."""
    return ast.unparse(_strip_docstrings(ast.parse(text, filename=filename)))


@functools.lru_cache(maxsize=None)
def normalised_source(path: Path) -> str:
    """The module's code without comments, docstrings or formatting (:func:`_normalised`)."""
    return _normalised(Path(path).read_text(), str(path))


def _portable(value) -> str:
    """``repr`` of a constant, a path inside the repository written relative to it (a clone
    elsewhere has the same fingerprints)."""
    if isinstance(value, Path):
        try:
            return repr(value.resolve().relative_to(ROOT).as_posix())
        except ValueError:
            return repr(str(value))
    return repr(value)


def source_fingerprint(namespace: dict, *objects) -> str:
    """SHA-256 of a driver stage's own code, finer than its module's import closure: the public
    constants of ``namespace`` (a module's ``globals()``: upper-case names not starting with
    ``_``, paths relative to the repository) and the normalised source of ``objects`` (functions
    or classes, without comments or docstrings, as :func:`normalised_source`)."""
    consts = {k: _portable(v) for k, v in namespace.items() if k.isupper() and not k.startswith("_")}
    h = hashlib.sha256(json.dumps(consts, sort_keys=True).encode())
    for o in objects:
        h.update(b"\0" + _normalised(textwrap.dedent(inspect.getsource(o))).encode())
    return h.hexdigest()


def module_imports(path: Path, name: str) -> set[str]:
    """Modules of ours that ``name`` (at ``path``) imports, anywhere in the file."""
    is_package = path.name == "__init__.py"
    package = name if is_package else name.rpartition(".")[0]
    out: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
        if isinstance(node, ast.Import):
            out.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                parts = package.split(".")
                base = ".".join(parts[: len(parts) - node.level + 1])
                base = f"{base}.{node.module}" if node.module else base
            else:
                base = node.module or ""
            for alias in node.names:
                sub = f"{base}.{alias.name}"
                # ``from pkg import submodule`` depends on the submodule; ``from pkg import name``
                # on the package (its __init__), which re-exports the name.
                out.add(sub if module_path(sub) is not None else base)
    return {m for m in out if module_path(m) is not None and m not in NOT_CODE}


def code_closure(modules: Sequence[str]) -> list[str]:
    """Sorted dotted names of ``modules`` and every module of ours they import, transitively."""
    seen: set[str] = set()
    todo = list(modules)
    while todo:
        m = todo.pop()
        if m in seen:
            continue
        path = module_path(m)
        if path is None:
            raise ValueError(f"{m}: not a module of {OWN_PACKAGES}")
        seen.add(m)
        todo.extend(module_imports(path, m) - seen)
    return sorted(seen)


def code_fingerprint(modules: Sequence[str]) -> str:
    """SHA-256 of the normalised source of the import closure of ``modules``."""
    h = hashlib.sha256()
    for m in code_closure(modules):
        h.update(m.encode() + b"\0" + normalised_source(module_path(m)).encode() + b"\0")
    return h.hexdigest()


def environment(packages: Sequence[str] = ("jax", "numpy", "scipy", "ompl", "toppra", "python-fcl", "trimesh",
                                           "yourdfpy", "pandas")) -> dict:
    """Python and package versions (recorded beside a fingerprint, not part of it)."""
    import platform
    from importlib import metadata

    out = {"python": platform.python_version()}
    for p in packages:
        try:
            out[p] = metadata.version(p)
        except metadata.PackageNotFoundError:
            pass
    return out
