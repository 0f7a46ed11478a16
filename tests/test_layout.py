"""The package layout: layers, no import cycle, every module in the README code map (AST only)."""

import re
from pathlib import Path

from experiments.fingerprints import module_imports

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


GRAPH = {m: {t for t in module_imports(p, m) if t.startswith("larc_jax.") and t != m}
         for m, p in ((_module(p), p) for p in PKG.rglob("*.py"))}
"""Each module of larc_jax -> the modules of larc_jax it imports, anywhere in the file (function-local
imports too; ``from package import submodule`` counts the submodule)."""


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
