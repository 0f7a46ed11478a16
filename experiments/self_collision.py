"""Allowed self-collision pairs (the SRDF ``disable_collisions`` list), computed the way MoveIt's
setup assistant does, and written to ``larc_jax/data/piper_allowed_collisions.yaml`` (package data,
:mod:`larc_jax.data`).

A link pair is *allowed* (never checked for self-collision) when it is

* ``adjacent``: parent/child in the URDF tree. Links rigidly joined through fixed joints form one
  body, so each inherits the other's neighbours; a link without collision geometry is bridged
  (its neighbours become adjacent to each other). For PIPER this gives the chain
  base_link-link1-...-link6 plus both fingers (link7, link8) with link6.
* ``default``: in contact at the all-zero configuration (MoveIt's "default" category; only
  listed if not already adjacent or always).
* ``always``: in contact in at least ``always_fraction`` (MoveIt's default 0.95) of the random
  configurations.
* ``never``: in contact in none of ``n_samples`` random configurations, drawn uniformly within
  the URDF limits of the active joints (fingers held closed) from ``seed``.

``python -m experiments.self_collision`` writes the file atomically; the contact count of each
sampled pair is recorded so the categorisation can be audited.
"""

from __future__ import annotations

import argparse
import itertools
import multiprocessing as mp
import os
import time
from pathlib import Path

import numpy as np
import yaml

from larc_jax.data import PIPER_ALLOWED_COLLISIONS, data_path

DEFAULT_PATH = data_path(PIPER_ALLOWED_COLLISIONS)
DEFAULT_SEED = 20270821
DEFAULT_SAMPLES = 10_000
ALWAYS_FRACTION = 0.95

__all__ = [
    "adjacent_pairs",
    "compute_allowed_pairs",
    "load_allowed_pairs",
    "load_allowed_file",
    "DEFAULT_PATH",
]


def _pair(a: str, b: str) -> tuple[str, str]:
    return tuple(sorted((a, b)))  # type: ignore[return-value]


def adjacent_pairs(robot, links_with_geometry=None) -> set[tuple[str, str]]:
    """MoveIt-style adjacency: joint-connected links, through fixed joints and geometry-less
    links. Returns sorted name pairs."""
    from larc_jax.model.robot import JointType

    names = list(robot.link_names)
    geo = set(names if links_with_geometry is None else links_with_geometry)
    # Rigid bodies: union links joined by fixed joints.
    group = {n: n for n in names}

    def find(x):
        while group[x] != x:
            group[x] = group[group[x]]
            x = group[x]
        return x

    for i in range(1, len(names)):
        if robot.joint_type[i] == JointType.FIXED:
            group[find(names[i])] = find(names[robot.parent[i]])
    # Graph between rigid bodies (movable joints).
    edges: dict[str, set[str]] = {find(n): set() for n in names}
    for i in range(1, len(names)):
        a, b = find(names[robot.parent[i]]), find(names[i])
        if a != b:
            edges[a].add(b)
            edges[b].add(a)
    members: dict[str, list[str]] = {}
    for n in names:
        members.setdefault(find(n), []).append(n)
    # Bodies without geometry are bridged: their neighbours become neighbours of each other.
    for body, mem in members.items():
        if not any(m in geo for m in mem):
            nb = list(edges[body])
            for x, y in itertools.combinations(nb, 2):
                edges[x].add(y)
                edges[y].add(x)
    out = set()
    for body, mem in members.items():
        for x, y in itertools.combinations(mem, 2):  # same rigid body
            out.add(_pair(x, y))
        for other in edges[body]:
            for x in mem:
                for y in members[other]:
                    out.add(_pair(x, y))
    return {p for p in out if p[0] in geo and p[1] in geo}


def _count_worker(args):
    Q, pairs = args
    from experiments.collision import CollisionModel

    model = CollisionModel()
    idx = [(model.link_names.index(a), model.link_names.index(b)) for a, b in pairs]
    counts = np.zeros(len(pairs), dtype=np.int64)
    for q in Q:
        counts += model.link_pair_contacts(q, idx)
    return counts


def compute_allowed_pairs(
    n_samples: int = DEFAULT_SAMPLES,
    seed: int = DEFAULT_SEED,
    *,
    workers: int = 2,
    always_fraction: float = ALWAYS_FRACTION,
    progress: bool = True,
) -> dict:
    """The allowed-pairs document (see module docstring)."""
    from experiments.collision import CollisionModel

    model = CollisionModel()
    robot = model.robot
    geo = model.links_with_geometry
    adjacent = adjacent_pairs(robot, geo)
    all_pairs = [_pair(a, b) for a, b in itertools.combinations(geo, 2)]
    sampled = [p for p in all_pairs if p not in adjacent]

    rng = np.random.default_rng(seed)
    lo, hi = np.asarray(robot.q_lower, float), np.asarray(robot.q_upper, float)
    Q = rng.uniform(lo, hi, size=(n_samples, robot.n_joints))

    idx = [(model.link_names.index(a), model.link_names.index(b)) for a, b in sampled]
    default_contact = model.link_pair_contacts(np.zeros(robot.n_joints), idx)

    t0 = time.perf_counter()
    chunks = [c for c in np.array_split(Q, max(1, workers * 8)) if len(c)]
    counts = np.zeros(len(sampled), dtype=np.int64)
    if workers > 1:
        ctx = mp.get_context("spawn")
        with ctx.Pool(workers) as pool:
            it = pool.imap_unordered(_count_worker, [(c, sampled) for c in chunks])
            if progress:
                from tqdm import tqdm

                it = tqdm(it, total=len(chunks), desc="self-collision sampling", unit="chunk")
            for c in it:
                counts += c
    else:
        for c in chunks:
            counts += _count_worker((c, sampled))
    elapsed = time.perf_counter() - t0

    pairs = [{"a": a, "b": b, "reason": "adjacent"} for a, b in sorted(adjacent)]
    contact_counts = {}
    for (a, b), n, d in zip(sampled, counts, default_contact):
        contact_counts[f"{a}:{b}"] = int(n)
        if n >= always_fraction * n_samples:
            pairs.append({"a": a, "b": b, "reason": "always"})
        elif d:
            pairs.append({"a": a, "b": b, "reason": "default"})
        elif n == 0:
            pairs.append({"a": a, "b": b, "reason": "never"})
    checked = [f"{a}:{b}" for (a, b), n, d in zip(sampled, counts, default_contact)
               if 0 < n < always_fraction * n_samples and not d]
    return {
        "urdf_sha256": robot.urdf_sha256,
        "urdf": os.path.basename(robot.urdf_path),
        "method": "MoveIt setup-assistant style: adjacent + default + always (>= always_fraction) + never",
        "n_samples": int(n_samples),
        "seed": int(seed),
        "sampling": "uniform within the URDF limits of joint1..joint6 (numpy default_rng(seed)); "
                    "fingers joint7/joint8 held at 0 (closed)",
        "always_fraction": float(always_fraction),
        "elapsed_s": round(elapsed, 2),
        "pairs": pairs,
        "checked_pairs": checked,
        "contact_counts": contact_counts,
    }


def write_allowed_file(doc: dict, path: str | Path = DEFAULT_PATH) -> None:
    from larc_jax.io import atomic_write_text

    header = (
        "# Allowed self-collision pairs (SRDF disable_collisions equivalent), written by\n"
        "# `python -m experiments.self_collision`. See that module for the rules.\n"
    )
    atomic_write_text(path, header + yaml.safe_dump(doc, sort_keys=False, default_flow_style=None, width=120))


def load_allowed_file(path: str | Path = DEFAULT_PATH, robot=None, *, check_hash: bool = True) -> dict:
    """Read the allowed-pairs file; with ``robot`` given, check it was made for its URDF."""
    path = Path(path)
    doc = yaml.safe_load(path.read_text())
    if not isinstance(doc, dict) or "pairs" not in doc:
        raise ValueError(f"{path}: expected a mapping with 'pairs'")
    if robot is not None and check_hash and doc.get("urdf_sha256") != robot.urdf_sha256:
        raise ValueError(
            f"{path}: computed for a URDF with sha256 {doc.get('urdf_sha256')}, but "
            f"{robot.urdf_path} has sha256 {robot.urdf_sha256}; rerun python -m experiments.self_collision"
        )
    return doc


def load_allowed_pairs(path: str | Path = DEFAULT_PATH, robot=None, *, check_hash: bool = True) -> frozenset:
    """Allowed pairs as a frozenset of sorted (link, link) name tuples."""
    from experiments.collision import normalise_pairs

    return normalise_pairs(load_allowed_file(path, robot, check_hash=check_hash)["pairs"])


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("-o", "--output", default=str(DEFAULT_PATH))
    ap.add_argument("--samples", type=int, default=DEFAULT_SAMPLES)
    ap.add_argument("--seed", type=int, default=DEFAULT_SEED)
    ap.add_argument("--workers", type=int, default=2)
    args = ap.parse_args(argv)
    t0 = time.perf_counter()
    doc = compute_allowed_pairs(args.samples, args.seed, workers=args.workers)
    write_allowed_file(doc, args.output)
    reasons = {}
    for p in doc["pairs"]:
        reasons[p["reason"]] = reasons.get(p["reason"], 0) + 1
    print(f"wrote {args.output}: {len(doc['pairs'])} allowed pairs {reasons}; "
          f"still checked: {doc['checked_pairs']}; {time.perf_counter() - t0:.1f} s")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
