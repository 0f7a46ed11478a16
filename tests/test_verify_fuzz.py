"""Fuzz test of the independent checker (issue 18, deliverable 6): over 1,000 deterministically
mutated certificates, ``verify_certificate`` either refutes (``Refuted``, exit 1), refuses
(``LarcInputError``, exit 2) or verifies, and never raises anything else (exit 3). A mutant it
verifies must still make a true claim, which this file re-checks with its own reading of the
certificate (:func:`read_claim`, strict): either the claim is implied by the original
certificate's (same files, a margin no larger, more links excluded, ...: :func:`implied`; the
original is itself re-checked independently), or :func:`claim_holds` re-proves it leaf by leaf
with the NumPy leaf test. A sample of mutants also goes through ``larc verify`` (exit 0, 1 or 2,
one stderr line, no traceback).
"""

from __future__ import annotations

import copy
import dataclasses
import json
import math
import os
import random
import subprocess
import sys
import time
import traceback
from pathlib import Path

import numpy as np
import pytest

import larc_jax.products.verify as verify_module
from larc_jax.products.certificate import hexf, scene_sha256
from larc_jax.drivers.cli import EXIT_BAD_INPUT, EXIT_OK, EXIT_REFUTED, main
from larc_jax.enclosure import default_capsule_path
from larc_jax.errors import LarcInputError
from larc_jax.leaf.interval import dyadic_ends
from larc_jax.model.scene import read_scene
from larc_jax.products.verify import Refuted, verify_certificate

from .verify_oracle import Unreadable, cached_robot_load, claim_holds, implied, read_claim

ROOT = Path(__file__).resolve().parent.parent
EX = ROOT / "configs" / "examples"
REACH, SWEEP, CELL = (str(EX / n) for n in ("reach_left.yaml", "sweep_front.yaml", "cell.yaml"))
SEED = 18
N_MUTANTS = {"cascade": 650, "assumptions": 400}  # 1,050 in all


@pytest.fixture(scope="module")
def bases(tmp_path_factory):
    """Two small real certificates (the NumPy reference method, depth 4): the hull cascade with
    reach_left certified and sweep_front not; and the capsule test with a stated gripper, a
    tracking tolerance and the self test. Also an empty scene file a mutant may point to."""
    d = tmp_path_factory.mktemp("fuzz")
    common = ["--scene", CELL, "--max-depth", "4", "--method", "reference", "-q"]
    # 1 mm of padding: with the cascade's default (none) the capsule test alone passes reach_left.
    assert main(["certify", REACH, SWEEP, *common, "--padding", "0.001", "--no-fail-on-uncertified", "--certificate",
                 str(d / "cascade.json")]) == EXIT_OK
    assert main(["certify", REACH, *common, "--enclosure", "capsules", "--hold", "joint7=0", "--hold", "joint8=0",
                 "--tracking-tolerance", "0.002", "--self-collision", "--certificate",
                 str(d / "assumptions.json")]) == EXIT_OK
    (d / "empty.yaml").write_text("frame: base_link\nboxes: []\n")
    docs = {k: json.loads((d / f"{k}.json").read_text()) for k in N_MUTANTS}
    assert [t["certified"] for t in docs["cascade"]["trajectories"]] == [True, False]
    assert 2 in docs["cascade"]["trajectories"][0]["leaves"]["stage"]  # the hull stage decided a leaf
    return d, docs


@pytest.fixture(scope="module")
def cached_robot_loads():
    """Loading PIPER (motion constants, mesh hashes) is most of a verify call: the same robot
    file loaded with the same arguments gives the same robot, and the same robot the same mesh
    hashes, and the same robot and capsules the same containment proof, so repeated identical
    calls are served from a cache (any other call, and every failure, runs for real; no file
    changes during the test)."""
    load, geometry, seen = verify_module.load_robot_file, verify_module.collision_geometry, {}
    prove, proven = verify_module.prove_enclosures, {}

    def cached_geometry(robot):
        if id(robot) not in seen:
            seen[id(robot)] = (robot, geometry(robot))  # the robot is kept: its id is not reused
        return seen[id(robot)][1]

    def cached_proof(robot, capsules, hull, **kw):
        # the containment proof of one robot and capsule model (a success only; both objects kept, so
        # their ids are not reused): the same objects give the same proof
        key = (id(robot), id(capsules), bool(hull))
        if key not in proven:
            proven[key] = (robot, capsules, prove(robot, capsules, hull, **kw))
        return proven[key][2]

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(verify_module, "load_robot_file", lambda *a, **k: cached_robot_load(load, *a, **k))
        mp.setattr(verify_module, "collision_geometry", cached_geometry)
        mp.setattr(verify_module, "prove_enclosures", cached_proof)
        yield


# ----------------------------------------------------------------------------------------------
# Mutations (seeded): each returns a description; some edit the JSON text itself
# ----------------------------------------------------------------------------------------------

HOSTILE_FLOATS = ["0x1p+1024", "-0x1p+1024", "0x1.fffffffffffffp+1023", "0x1p-1075", "0x1p+99999999999999999999",
                  "nan", "inf", "-inf", "-0x0p+0", "0x", "", "zero", "1e400", "0x" + "f" * 400, " 0x1p-7 ", "0X1P-7"]
HOSTILE_INTS = [-1, 0, 1, 2**31, 2**63 - 1, 2**63, 2**64, -2**63 - 1, 10**30, 10**400]
OTHER_TYPES = [None, True, False, 0, -1, 1.5, "", "x", [], {}, [None], {"x": 1}, float("nan"), float("inf")]


@dataclasses.dataclass(frozen=True)
class Context:
    base: str
    """The original certificate (JSON text)."""
    empty: str
    """An empty scene file, and the hash of its boxes."""
    empty_sha256: str
    margin_m: float
    """The original's margin."""


def _nodes(doc, path=()):
    yield path, doc
    items = doc.items() if isinstance(doc, dict) else enumerate(doc) if isinstance(doc, list) else ()
    for k, v in items:
        yield from _nodes(v, path + (k,))


def _set(doc, path, value):
    for k in path[:-1]:
        doc = doc[k]
    doc[path[-1]] = value


def _is_hex(v) -> bool:
    try:
        return isinstance(v, str) and ("0x" in v or v in ("inf", "-inf", "nan")) and float.fromhex(v) is not None
    except ValueError:
        return False


def _perturb(rng, x: float) -> float:
    how = rng.randrange(8)
    if how < 2:
        return float(np.nextafter(x, math.inf if how else -math.inf))
    if how == 2:
        return x + rng.randint(2, 1000) * math.ulp(x) * rng.choice((-1, 1))
    return x * rng.choice((1 + 1e-9, 1 - 1e-9, 1.001, 0.999, 2.0, 0.5, -1.0, 0.0, 1e-6, 1e6))


def _pick(rng, doc, test):
    found = [(p, v) for p, v in _nodes(doc) if p and test(p, v)]
    return rng.choice(found) if found else (None, None)


def _mut_float(rng, doc, ctx):
    p, v = _pick(rng, doc, lambda p, v: _is_hex(v))
    if p is None:
        return "no float"
    new = hexf(_perturb(rng, float.fromhex(v))) if rng.random() < 0.7 else rng.choice(HOSTILE_FLOATS)
    _set(doc, p, new)
    return f"{'/'.join(map(str, p))}: {v} -> {new[:30]}"


def _mut_int(rng, doc, ctx):
    p, v = _pick(rng, doc, lambda p, v: isinstance(v, int) and not isinstance(v, bool))
    if p is None:
        return "no int"
    new = v + rng.choice((-1, 1, -2, 2, 16)) if rng.random() < 0.5 else rng.choice(HOSTILE_INTS)
    _set(doc, p, new)
    return f"{'/'.join(map(str, p))}: {v} -> {str(new)[:30]}"


def _mut_type(rng, doc, ctx):
    p, v = _pick(rng, doc, lambda p, v: True)
    new = copy.deepcopy(rng.choice(OTHER_TYPES))
    _set(doc, p, new)
    return f"{'/'.join(map(str, p))}: {type(v).__name__} -> {new!r}"


def _mut_bool(rng, doc, ctx):
    p, v = _pick(rng, doc, lambda p, v: isinstance(v, bool))
    _set(doc, p, not v)
    return f"{'/'.join(map(str, p))}: {v} -> {not v}"


def _mut_dict(rng, doc, ctx):
    p, d = _pick(rng, doc, lambda p, v: isinstance(v, dict) and v)
    if p is None:
        return "no dict"
    key = rng.choice(sorted(d))
    if rng.random() < 0.5:
        del d[key]
        return f"{'/'.join(map(str, p))}: dropped '{key}'"
    d[rng.choice(("zz_unknown", key.upper(), key + "s"))] = copy.deepcopy(d[key])
    return f"{'/'.join(map(str, p))}: added a key beside '{key}'"


def _mut_list(rng, doc, ctx):
    p, lst = _pick(rng, doc, lambda p, v: isinstance(v, list) and v)
    if p is None:
        return "no list"
    how, k = rng.randrange(6), rng.randrange(len(lst))
    if how == 0:
        del lst[k]
    elif how == 1:
        lst.insert(k, copy.deepcopy(lst[k]))
    elif how == 2:
        j = rng.randrange(len(lst))
        lst[k], lst[j] = lst[j], lst[k]
    elif how == 3:
        lst.reverse()
    elif how == 4:
        lst.clear()
    else:
        lst.append(copy.deepcopy(rng.choice(OTHER_TYPES)))
    return f"{'/'.join(map(str, p))}: list edit {how} at {k}"


def _mut_leaves(rng, doc, ctx):
    """Edit one trajectory's leaf cover consistently across its columns."""
    t = rng.choice(doc["trajectories"])
    lv = t["leaves"]
    n = len(lv["t0"])
    k = rng.randrange(n)
    how = rng.randrange(4)
    if how == 0:  # split a leaf into its two dyadic halves (the stored values copied)
        ta, tb = float.fromhex(t["t_start"]), float.fromhex(t["t_end"])
        d, i = lv["depth"][k] + 1, 2 * lv["index"][k]
        ends = [float(x) for x in dyadic_ends(ta, tb, d, i)] + [float(dyadic_ends(ta, tb, d, i + 1)[1])]
        for key, col in lv.items():
            col.insert(k + 1, copy.deepcopy(col[k]))
        lv["depth"][k] = lv["depth"][k + 1] = d
        lv["index"][k], lv["index"][k + 1] = i, i + 1
        lv["t0"][k], lv["t1"][k], lv["t0"][k + 1], lv["t1"][k + 1] = (hexf(ends[0]), hexf(ends[1]), hexf(ends[1]),
                                                                       hexf(ends[2]))
    for key, col in lv.items():
        if how == 1:
            del col[k]
        elif how == 2:
            col.insert(k, copy.deepcopy(col[k]))
        elif how == 3 and k + 1 < n:
            col[k], col[k + 1] = col[k + 1], col[k]
    return f"trajectory {t['id']!r}: leaf edit {how} at {k}"


def _mut_parameters(rng, doc, ctx):
    p, r = doc["parameters"], doc["robot"]
    how = rng.randrange(10)
    if how == 0 and rng.random() < 0.5:
        p["margin_m"] = ctx.margin_m * rng.choice((0.5, 1 - 1e-9, 1 + 1e-9, 0.999, 1.001, 2, 1e-3))
    elif how == 0:  # a smaller padding is a weaker claim, a larger one a stronger (and false) one
        p["padding_m"] = rng.choice((0.0, 1e-12, 0.0005, 0.001 * (1 - 1e-9), 0.001 * (1 + 1e-9), 0.003, -0.001, "0.001"))
    elif how == 1:
        p["max_depth"] = rng.choice((0, 1, 3, 5, 30, 62, 63, 64, 65))
    elif how == 2:
        p["enclosure"] = rng.choice(("hull", "capsules", "swept", "HULL"))
    elif how == 3:
        p["dtype"] = rng.choice(("float32", "float64", "float16"))
    elif how == 4:
        p["ignore_links"] = p["ignore_links"] + [rng.choice(("link6", "base_link", "gripper_base", "nope"))]
    elif how == 5:
        stated = rng.choice(({}, {"joint7": 0.0}, {"joint7": -0.038, "joint8": 0.0}, {"joint1": 0.0}, {"nope": 0.0}))
        r["stated_joints"] = {j: hexf(x) for j, x in stated.items()}
        if rng.random() < 0.7:  # the run spec's record of them too (else the two disagree)
            p["hold"] = stated
    elif how == 6:
        p["tracking_tolerance"] = rng.choice((None, {"joint1": 0.001}, {"nope": 0.001}, 0.002, 0.0, [0.002] * 3, {
            j: rng.choice((0.0, 1e-12, 0.001, 0.002, 0.002 * (1 + 1e-9), 0.004)) for j in r["active_joints"]}))
    elif how == 7:
        p["self_collision"], p["self_margin_m"], p["self_skip"] = rng.choice(
            ((False, 0.0, []), (True, 0.0, []), (True, 0.01, ["link1:link2"]), (False, 0.01, [])))
    elif how == 8:
        p[rng.choice(("method", "velocities", "coarse_depth"))] = rng.choice(
            ("larc", "reference", "recorded", "finite-difference", 3, "nope", None))
    else:
        r["file"] = rng.choice((None, str(default_capsule_path()), os.path.relpath(default_capsule_path()),
                                str(ROOT / "nope.yaml"), REACH, "/dev/null", "/"))
    return f"parameter edit {how}"


def _mut_files(rng, doc, ctx):
    """Hashes, paths, ids, claims and scenes: the labels an attacker may swap."""
    trajs, how = doc["trajectories"], rng.randrange(8)
    t = rng.choice(trajs)
    if how == 0:
        p, v = _pick(rng, doc, lambda p, v: isinstance(p[-1], str) and p[-1].endswith("sha256") and isinstance(v, str))
        _set(doc, p, rng.choice((v[:-1] + ("0" if v[-1] != "0" else "1"), v.upper(), "", None, "0" * 64)))
    elif how == 1:
        t["file"] = rng.choice((REACH, SWEEP, CELL, str(EX), "/dev/null", "nope.yaml", os.path.relpath(REACH)))
    elif how == 2:
        doc["scenes"][0]["file"] = rng.choice((REACH, str(EX / "pick.scene"), "/dev/null", os.path.relpath(CELL)))
    elif how == 3:
        t["id"] = rng.choice([u["id"] for u in trajs] + ["", "x\ny"])
    elif how == 4:  # claim everything
        for u in trajs:
            u["certified"] = True
            u["leaves"]["certified"] = [True] * len(u["leaves"]["certified"])
    elif how == 5:  # a second, empty scene, pointed at by one trajectory
        doc["scenes"].append({"file": ctx.empty, "sha256": None, "arrays_sha256": ctx.empty_sha256,
                              "name": "empty", "boxes": []})
        t["scene"] = len(doc["scenes"]) - 1
    elif how == 6:
        t["velocities"] = rng.choice(("finite-difference", "recorded", None, "", "nope"))
    else:
        other = rng.choice(trajs)  # another trajectory's file and hashes under this label
        t.update({k: other[k] for k in ("file", "sha256", "arrays_sha256")})
    return f"label edit {how} on {t['id']!r}"


def _mut_text(rng, text: str):
    how = rng.randrange(6)
    if how == 0:
        return text[:rng.randrange(len(text))], "truncated"
    if how == 1:
        k = rng.randrange(len(text))
        return text[:k] + chr(rng.randrange(32, 127)) + text[k + 1:], f"char {k} replaced"
    if how == 2:
        return "[" * 100_000 + "]" * 100_000, "deep nesting"
    if how == 3:
        return text.replace('"margin_m"', '"margin_m": "0x1p-1", "margin_m"', 1), "duplicate key"
    if how == 4:
        return "\ufeff" + text, "byte order mark"
    return "", "empty"


MUTATIONS = [(_mut_float, 5), (_mut_int, 3), (_mut_type, 2), (_mut_bool, 1), (_mut_dict, 2), (_mut_list, 2),
             (_mut_leaves, 3), (_mut_parameters, 3), (_mut_files, 3)]


def _apply(op, rng, doc, ctx) -> str:
    try:
        return op(rng, doc, ctx)
    except (KeyError, IndexError, TypeError, ValueError, AttributeError, OverflowError):
        return f"{op.__name__} skipped (an earlier edit removed its target)"


def mutants(ctx: Context, n: int, seed):
    """``n`` (text, description) mutants of ``ctx.base``: 1 to 3 tree edits, sometimes a text edit."""
    rng = random.Random(str(seed))
    ops, weights = zip(*MUTATIONS)
    for _ in range(n):
        doc = json.loads(ctx.base)
        what = [_apply(op, rng, doc, ctx) for op in rng.choices(ops, weights, k=rng.choice((1, 1, 2, 3)))]
        text = json.dumps(doc, indent=1)
        if rng.random() < 0.06:
            text, w = _mut_text(rng, text)
            what.append(w)
        yield text, "; ".join(what)


# ----------------------------------------------------------------------------------------------
# The tests
# ----------------------------------------------------------------------------------------------


def _context(d: Path, base: dict) -> Context:
    empty = str(d / "empty.yaml")
    margin_m = base["parameters"]["margin_m"]
    return Context(json.dumps(base), empty, scene_sha256(read_scene(empty)), margin_m)


def _outcome(path):
    try:
        verify_certificate(path)
        return "verified", None
    except Refuted as exc:
        return "refuted", str(exc)
    except LarcInputError as exc:
        return "bad input", str(exc)
    except Exception as exc:  # noqa: BLE001 - what the CLI reports as exit 3
        frames = [f for f in traceback.extract_tb(exc.__traceback__) if "larc_jax" in f.filename]
        where = f"{Path(frames[-1].filename).name}:{frames[-1].lineno} {frames[-1].name}" if frames else "?"
        return "crash", f"{type(exc).__name__} at {where}: {str(exc)[:80]}"


def _judge(base_claim, text: str, outcome: str, message) -> tuple[str, str]:
    """``(kind, detail)``: kind ``ok`` (refuted or refused in one line, or a true claim
    verified, ``detail`` saying how it was found true) or the kind of failure."""
    if outcome == "crash":
        return "exit 3", message
    if outcome != "verified":
        return ("ok", outcome) if "\n" not in message else ("message spans lines", f"{outcome}: {message[:80]!r}")
    try:
        claim = read_claim(text)
    except Unreadable as exc:
        return "verified what the format does not allow", str(exc)
    if implied(claim, base_claim):
        return "ok", "verified (implied by the original)"
    why = claim_holds(claim)
    return ("ok", "verified (re-proved)") if why is None else ("verified a false claim", why)


@pytest.mark.parametrize("name", list(N_MUTANTS))
def test_oracle_accepts_the_original_and_rejects_false_claims(bases, name):
    """The oracle can fail: it accepts each original certificate (re-proved from its files) but not
    a false claim (everything claimed, a leaf dropped, a margin five times larger)."""
    d, docs = bases
    base = docs[name]
    claim = read_claim(json.dumps(base))
    assert implied(claim, claim) and claim_holds(claim) is None
    everything, dropped, margin = (copy.deepcopy(base) for _ in range(3))
    for t in everything["trajectories"]:
        t["certified"] = True
    for col in dropped["trajectories"][0]["leaves"].values():
        del col[1]
    margin["parameters"]["margin_m"] = 5 * base["parameters"]["margin_m"]
    for doc, why in ((dropped, "do not cover"), (margin, "fails")) + (((everything, "fails"),) if name == "cascade"
                                                                       else ()):
        false = read_claim(json.dumps(doc))
        assert not implied(false, claim)
        assert why in claim_holds(false)
        assert _judge(claim, json.dumps(doc), "verified", None)[0] == "verified a false claim"


@pytest.mark.parametrize("name", list(N_MUTANTS))
def test_mutated_certificates_verify_only_true_claims(bases, cached_robot_loads, name, tmp_path):
    d, docs = bases
    ctx = _context(d, docs[name])
    base_claim = read_claim(json.dumps(docs[name]))
    counts, failures, start = {}, {}, time.perf_counter()
    path = tmp_path / "mutant.json"
    for i, (text, what) in enumerate(mutants(ctx, N_MUTANTS[name], (SEED, name))):
        path.write_text(text)
        kind, detail = _judge(base_claim, text, *_outcome(path))
        key = detail if kind == "ok" else kind
        counts[key] = counts.get(key, 0) + 1
        if kind != "ok":  # grouped by kind and where (a crash) or why (else)
            failures.setdefault((kind, detail.split(": ")[0][:50]), []).append(f"mutant {i} ({what}): {detail}")
    print(f"{name}: {sum(counts.values())} mutants in {time.perf_counter() - start:.1f} s: {counts}")
    assert not failures, f"{len(failures)} distinct failures ({counts}):\n" + "\n".join(
        f"[{kind}, {len(v)}x] {v[0]}" for (kind, _), v in failures.items())
    # Not a degenerate run: every outcome occurs, and the oracle's re-proof runs.
    assert counts.get("refuted", 0) >= 100 and counts.get("bad input", 0) >= 50
    assert counts.get("verified (implied by the original)", 0) >= 30 and counts.get("verified (re-proved)", 0) >= 1


def test_cli_exit_codes_on_mutants(bases, tmp_path, capsys):
    """Twenty mutants through `larc verify` in this process (exit 0, 1 or 2 and a single stderr line),
    and two of the issue's hostile inputs through the real command (in parallel)."""
    d, docs = bases
    for i, (text, what) in enumerate(mutants(_context(d, docs["cascade"]), 20, (SEED, "cli"))):
        path = tmp_path / f"m{i}.json"
        path.write_text(text)
        rc = main(["verify", str(path), "-q"])
        err = capsys.readouterr().err
        assert rc in (EXIT_OK, EXIT_REFUTED, EXIT_BAD_INPUT) and "Traceback" not in err, f"{what}: {err}"
        assert len(err.strip().splitlines()) == 1 or (rc == EXIT_OK and not err.strip()), f"{what}: {err}"
    overflow = copy.deepcopy(docs["cascade"])
    overflow["parameters"]["margin_m"] = "0x1p+1024"
    (d / "overflow.json").write_text(json.dumps(overflow))
    huge = copy.deepcopy(docs["cascade"])
    huge["trajectories"][0]["leaves"]["index"][0] = 2**63
    (d / "huge.json").write_text(json.dumps(huge))
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")]))
    procs = [subprocess.Popen([sys.executable, "-m", "larc_jax.drivers.cli", "verify", str(d / f)], env=env, text=True,
                              stdout=subprocess.PIPE, stderr=subprocess.PIPE) for f in ("overflow.json", "huge.json")]
    for proc in procs:
        out, err = proc.communicate(timeout=120)
        assert proc.returncode in (EXIT_REFUTED, EXIT_BAD_INPUT) and "Traceback" not in err, err
        assert len(err.strip().splitlines()) == 1, err
