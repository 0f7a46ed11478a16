"""The package layout: layers, no import cycle, every module in the README code map (AST only)."""

import ast
import re
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
PKG = ROOT / "larc_jax"
LAYERS = ("", "model", "enclosure", "obstacles", "leaf", "engine", "products", "drivers")
"""Subpackages from the bottom layer up ("" is the core: the top-level modules and data/)."""


def _module(path: Path) -> str:
    parts = list(path.relative_to(ROOT).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _layer(module: str) -> int:
    parts = module.split(".")
    sub = parts[1] if len(parts) > 2 or (len(parts) == 2 and (PKG / parts[1]).is_dir()) else ""
    return LAYERS.index(sub if sub != "data" else "")


def _imports(path: Path) -> set[str]:
    """Modules of larc_jax that ``path`` imports, anywhere in the file (function-local too)."""
    module = _module(path)
    package = module if path.name == "__init__.py" else module.rpartition(".")[0]
    out = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom):
            if node.level:
                parts = package.split(".")
                base = ".".join(parts[: len(parts) - node.level + 1])
                base = f"{base}.{node.module}" if node.module else base
            else:
                base = node.module or ""
            for alias in node.names:
                sub = f"{base}.{alias.name}"
                out.add(sub if (ROOT / Path(*sub.split("."))).with_suffix(".py").exists() else base)
        elif isinstance(node, ast.Import):
            out.update(a.name for a in node.names)
    return {m for m in out if m.startswith("larc_jax.") and m != module}


GRAPH = {_module(p): _imports(p) for p in PKG.rglob("*.py")}


def test_every_import_resolves_and_goes_down_the_layers():
    problems = []
    for module, targets in sorted(GRAPH.items()):
        for target in sorted(targets):
            path = ROOT / Path(*target.split("."))
            if not (path.with_suffix(".py").exists() or (path / "__init__.py").exists()):
                problems.append(f"{module} imports a missing {target}")
            elif not module.endswith("larc_jax") and _layer(target) > _layer(module):
                problems.append(f"{module} (layer {LAYERS[_layer(module)]!r}) imports {target} from above")
    assert not problems, "\n".join(problems)


def test_no_import_cycle():
    state: dict[str, int] = {}
    cycles = []

    def visit(module, stack):
        state[module] = 1
        for target in GRAPH.get(module, ()):
            if target == "larc_jax":
                continue
            if state.get(target) == 1:
                cycles.append(" -> ".join(stack[stack.index(target):] + [target]))
            elif target not in state:
                visit(target, stack + [target])
        state[module] = 2

    for module in sorted(GRAPH):
        if module not in state:
            visit(module, [module])
    assert not cycles, cycles


def test_readme_code_map_has_one_row_per_module():
    readme = (ROOT / "README.md").read_text()
    section = readme[readme.index("## Code map"):readme.index("Drivers (`experiments/`")]
    rows = re.findall(r"^\| `([^`]+)` \|", section, flags=re.M)
    modules = sorted(str(p.relative_to(PKG)) for p in PKG.rglob("*.py")
                     if p.name != "__init__.py" and p.parent.name != "data")
    assert sorted(r for r in rows if r.endswith(".py")) == modules
    assert all(len(p.read_text().splitlines()) <= 500 for p in PKG.rglob("*.py"))
