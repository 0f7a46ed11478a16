"""The fast path of the YAML reader (:mod:`larc_jax.plain_yaml`) returns exactly what the full
loader returns, or ``None`` so that the full loader runs: on random documents whose scalars are
YAML 1.1's traps (octal, sexagesimal, ``1e5`` as a string, ``-0.0``, ``.nan``, ``yes``, dates),
in block and flow style, on named edge cases, and on every YAML file the repository holds."""

from __future__ import annotations

import math
import random
from pathlib import Path

import numpy as np
import pytest
import yaml

import larc_jax.io as lio
from larc_jax.errors import LarcInputError
from larc_jax.plain_yaml import plain_documents

ROOT = Path(__file__).resolve().parent.parent
PLANNED = ROOT / "results" / "tightness" / "dataset" / "pad00mm" / "trajectories" / "easy_window" \
    / "easy_window_p01_ompl_planned.yaml"

TOKENS = [
    "0", "1", "-1", "+1", "017", "0o17", "0x1F", "0b101", "1_000", "1:30", "-190:20:30", "1.5", "-0.0", "+0.0",
    "0.1", "1.", ".5", "-.5", "1.0e+5", "1.0e5", "1e5", "1E-3", "6.02E+23", "1_0.5", "190:20:30.15", ".inf", "-.Inf",
    "+.INF", ".nan", ".NaN", "yes", "No", "on", "OFF", "y", "n", "true", "False", "~", "null", "Null", "",
    "2001-12-14", "2001-12-14t21:59:43.10-05:00", "2001-12-14 21:59:43.10", "'quoted'", '"1.0"', "'017'",
    '"yes"', "abc", "joint1", "a b", "0.1234567890123456789", "-1.7976931348623157e+308", "4.9e-324",
    "12345678901234567890", "=", "'<<'", "x<<", "nan", "inf", "-", "0.", "00", "09",
]
"""Plain scalars as they appear in a file: each resolves by YAML 1.1's implicit rules."""


def full(text: str):
    """What the full loader returns for ``text``, or the exception type it raises."""
    try:
        return list(yaml.load_all(text, Loader=lio.SafeYamlLoader))
    except Exception as exc:  # noqa: BLE001 - any refusal is a refusal
        return type(exc)


def same(a, b) -> bool:
    """Equality that counts NaN equal to NaN and tells -0.0 from 0.0 and 1 from 1.0 and True."""
    if type(a) is not type(b):
        return False
    if isinstance(a, float):
        return (math.isnan(a) and math.isnan(b)) or (a == b and math.copysign(1, a) == math.copysign(1, b))
    if isinstance(a, list):
        return len(a) == len(b) and all(same(x, y) for x, y in zip(a, b))
    if isinstance(a, dict):
        return len(a) == len(b) and all(same(ka, kb) and same(va, vb)
                                        for (ka, va), (kb, vb) in zip(a.items(), b.items()))
    return a == b


def check(text: str) -> bool:
    """The fast path agrees with the full loader on ``text``; True when it took the text."""
    fast = plain_documents(text, lio.SafeYamlLoader, lio.MAX_NESTING, len(text) + 1000)
    ref = full(text)
    if fast is None:
        return False
    assert isinstance(ref, list), f"fast path built {fast!r} where the full loader raises {ref}: {text!r}"
    assert same(fast, ref), f"{text!r}: fast {fast!r} != full {ref!r}"
    return True


def _random_text(rng: random.Random, depth: int, indent: int = 0) -> str:
    """A random YAML text: block or flow lists and mappings of raw scalar tokens."""
    pad = " " * indent
    kind = rng.choice(["scalar", "flow_list", "flow_map", "block_list", "block_map"] if depth else ["scalar"])
    if kind == "scalar":
        tok = rng.choice(TOKENS)
        return tok if tok else "''"
    n = rng.randint(0, 4)
    if kind == "flow_list":
        return "[" + ", ".join(_flow(rng, depth - 1) for _ in range(n)) + "]"
    if kind == "flow_map":
        return "{" + ", ".join(f"{_key(rng)}: {_flow(rng, depth - 1)}" for _ in range(n)) + "}"
    if n == 0:
        return "[]" if kind == "block_list" else "{}"
    lines = []
    for _ in range(n):
        child = _random_text(rng, depth - 1, indent + 2)
        nested = child.startswith("\n")
        if kind == "block_list":
            lines.append(f"{pad}-{'' if nested else ' '}{child}")
        else:
            lines.append(f"{pad}{_key(rng)}:{'' if nested else ' '}{child}")
    return "\n" + "\n".join(lines)


def _flow(rng: random.Random, depth: int) -> str:
    if depth <= 0 or rng.random() < 0.6:
        tok = rng.choice(TOKENS)
        return tok if tok else "''"
    return rng.choice(["[" + ", ".join(_flow(rng, depth - 1) for _ in range(rng.randint(0, 3))) + "]",
                       "{" + ", ".join(f"{_key(rng)}: {_flow(rng, depth - 1)}" for _ in range(rng.randint(0, 3))) + "}"])


def _key(rng: random.Random) -> str:
    return rng.choice(["a", "b", "c", "positions", "1", "1.0", "yes", "~", "'q'", "017", "x y"])


def test_random_documents_agree_with_the_full_loader():
    rng = random.Random(20261204)
    taken = 0
    for _ in range(3000):
        text = _random_text(rng, rng.randint(0, 4)).lstrip("\n")
        if rng.random() < 0.2:
            text = text + "\n---\n" + _random_text(rng, 2).lstrip("\n")
        taken += check(text)
    # duplicate keys and '=' make some texts fall back; most must be taken, or the test is empty
    assert taken > 1500


@pytest.mark.parametrize("value", [
    [1.5, -0.0, 1e5, "1e5", float("inf"), float("nan"), 2**70, True, None, "017", "", " a"],
    {"joint_names": ["joint1", "joint2"], "points": [{"positions": [0.1, -0.2], "time_from_start": {"sec": 1}}]},
    {1: "a", 1.5: "b", None: "c", False: "d"},
    [[[[]]], {}, [{}], "---", "..."],
])
@pytest.mark.parametrize("flow", [True, False, None])
def test_dumped_documents_agree_with_the_full_loader(value, flow):
    assert check(yaml.safe_dump(value, default_flow_style=flow))


@pytest.mark.parametrize("text, taken", [
    ("a: 1\nb: [1.5, -0.0, .nan, -.inf, 1e5, 017, 0x1F, 1_000, 1:30, 2001-12-14]\n", True),
    ("", True),                              # no document
    ("---\n", True),                         # one empty document: None
    ("--- 1\n--- [2]\n...\n", True),         # several documents
    ("! 1.5\n", True),                       # the non-specific tag: a string, as the full loader says
    ("a: &x [1]\nb: *x\n", False),           # anchors and aliases
    ("!!float 1\n", False),                  # an explicit tag
    ("a: !!binary aGk=\n", False),
    ("base: {x: 1}\nd:\n  <<: {y: 2}\n", False),     # a merge key
    ("'<<': 1\n", True),                     # a quoted '<<' is a plain string key
    ("? [1, 2]\n: a\n", False),              # a complex key (the full loader refuses it)
    ("a: 1\na: 2\n", False),                 # a duplicate key (refused by the full loader)
    ("1: a\n1.0: b\n", False),               # equal keys of different types
    ("= \n", False),                         # the value tag has no constructor
    ("a: [1, 2\n", False),                   # not YAML
    ("\t- 1\n", False),
    ("a: " + "[" * 64 + "]" * 64 + "\n", False),   # 65 levels: the full loader's error
    ("[" * 64 + "]" * 64 + "\n", True),            # 64 levels: allowed
    ("12345678901234567890123\n", True),     # a big int
    ("1" * 5000 + "\n", False),              # more digits than int() reads: the full loader's error
])
def test_named_cases(text, taken):
    assert check(text) is taken


def test_refusals_are_the_full_loaders(tmp_path):
    """Texts the fast path leaves get the full loader's one-line errors."""
    for text, words in (("a: 1\na: 2\n", "duplicate key"), ("[" * 70 + "]" * 70, "nested more than 64"),
                        ("a: &x [*x]\n", "contain itself"), ("a: [1, 2\n", "not valid YAML")):
        with pytest.raises(LarcInputError, match=words):
            lio.parse_yaml_documents(text, "f.yaml")


def test_every_yaml_file_in_the_repository_agrees():
    files = sorted(p for d in ("configs", "larc_jax", "results") for p in (ROOT / d).rglob("*.yaml")
                   if p.stat().st_size < 2**20)[::3]   # every third: all kinds, a few seconds
    assert len(files) > 100
    taken = sum(check(p.read_text()) for p in files)
    assert taken >= 0.9 * len(files)


def test_a_planned_trajectory_takes_the_fast_path():
    """The case it exists for: a planner's trajectory file is plain."""
    assert check(PLANNED.read_text())


def test_parse_vector_equals_parsing_each_number():
    """``parse_vector``'s whole-list conversion gives each entry's ``parse_number``, bit for bit,
    and every refusal still names the entry (bools, strings, ints too large, NaN when finite)."""
    rng = random.Random(7)
    pool = [0, 1, -3, 2**53 + 1, 2**64 + 1, 10**400, 0.1, -0.0, 1e308, float("nan"), float("inf"), True, "1", None]
    for _ in range(2000):
        value = [rng.choice(pool) for _ in range(3)]
        finite = rng.random() < 0.5
        try:
            ref = np.array([lio.parse_number(v, "f", f"v[{i}]", finite=finite) for i, v in enumerate(value)])
        except LarcInputError as exc:
            with pytest.raises(LarcInputError) as got:
                lio.parse_vector(value, 3, "f", "v", finite=finite)
            assert str(got.value) == str(exc)
            continue
        out = lio.parse_vector(value, 3, "f", "v", finite=finite)
        assert out.dtype == np.float64 and out.shape == (3,)
        assert out.tobytes() == ref.tobytes() or (np.isnan(out) == np.isnan(ref)).all() and \
            (out[~np.isnan(out)].tobytes() == ref[~np.isnan(ref)].tobytes())
