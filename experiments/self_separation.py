"""Prove that a link pair can never touch, over the whole joint range: branch and bound in the joint
space of the joints between the two links, with FCL mesh distances and the motion constants.

Why. The self-collision certificate (:mod:`larc_jax.leaf.self_collision`) checks capsule pairs. A few
PIPER pairs that are *not* joined by a joint have capsules that overlap at every configuration
(base_link / link2, link3 / link5: the capsules are fat near the joints), although the meshes
never touch. Sampling 10^4 configurations (the allowed list, ``experiments.self_collision``) does
not prove that; this does, and the certificate skips only pairs proven here.

The proof, for links A and B with B a descendant of A. Their relative pose depends only on the
active joints J on the tree path between them (joints above A move both rigidly, joints below B
move neither). For a cell ``C = c +- h`` of the box of J's limits, and any configuration ``q``
in it, walk the straight joint-space path from ``c`` to ``q`` with A held still: every point of B
(inside B's capsules: proven containment) moves at most ``sum_{j in J} a_Bj |q_j - c_j| <=
sum_j a_Bj h_j`` (motion constants, :mod:`larc_jax.enclosure.motion`, valid at every
configuration; ``a_Bj`` the largest over B's capsules). So if the FCL distance between A's and
B's collision meshes at ``c`` exceeds that bound plus ``FCL_TOLERANCE_M``, no configuration of the
cell brings the meshes' surfaces together. Cells are bisected along the joint with the largest
``a_Bj h_j`` until every cell is proven (or a configuration is found where the surfaces touch,
or the cell budget runs out: then the pair is not proven). Surfaces apart everywhere on the
connected joint box (the limits widened by ``WIDEN_RAD``) means the solids' overlap cannot change, so one configuration where the
two meshes' bounding boxes are disjoint (checked) shows that neither mesh ever lies inside the
other. The recorded ``clearance_m`` is the smallest ``distance - bound - tolerance`` over the
cells (refined until it exceeds ``TARGET_CLEARANCE_M``): the certificate skips the pair only
for a self margin below it.

``python -m experiments.self_separation`` proves PIPER's pairs whose capsules always overlap and
writes ``larc_jax/data/piper_self_separation.yaml`` (with the URDF's and the meshes' SHA-256).
"""

from __future__ import annotations

import argparse
import math
import time
from pathlib import Path

import numpy as np

from larc_jax.data import PIPER_SELF_SEPARATION, data_path

WIDEN_RAD = 0.05
"""The proof covers the joint limits widened by this much (revolute joints): a Hermite curve may
overshoot a limit between waypoints; the certificate skips a proven pair only for trajectories
whose curve stays inside the proven ranges (:func:`larc_jax.leaf.self_collision.curve_ranges`)."""
TARGET_CLEARANCE_M = 0.001
"""Cells are refined until each proves this clearance (a proof serves self margins below it)."""
FCL_TOLERANCE_M = 1e-6
"""Subtracted from every FCL distance (its float64 rounding is far smaller)."""
DEFAULT_PAIRS = (("base_link", "link2"), ("link3", "link5"))
"""PIPER link pairs, not joined by a joint, whose capsules overlap at every configuration."""


def prove_pair(model, capsules, link_a: str, link_b: str, target_m: float = TARGET_CLEARANCE_M,
               max_cells: int = 1_000_000, progress=None) -> dict:
    """Branch and bound (module docstring) for ``link_a`` and its descendant ``link_b``: every cell
    is refined until it proves a clearance above ``target_m``. Returns a record: ``proven``,
    ``clearance_m`` (>= target_m), ``cells``, ``joints`` and, if not proven, ``why``."""
    from larc_jax.model.robot import JointType
    from larc_jax.leaf.self_collision import path_joints

    import fcl

    robot = model.robot
    ia, ib = robot.link_index(link_a), robot.link_index(link_b)
    if ia not in robot.ancestors(ib):
        raise ValueError(f"{link_a} is not an ancestor of {link_b}")
    path = path_joints(robot, ia, ib)
    J = [robot.q_index[i] for i in path if robot.q_index[i] >= 0]
    a_B = np.array([max(float(capsules.motion_a[c, j]) for c in range(capsules.n_capsules)
                        if capsules.link_names[c] == link_b) for j in J])
    widen = np.array([WIDEN_RAD if robot.joint_type[i] == JointType.REVOLUTE else 0.0
                      for i in path if robot.q_index[i] >= 0])
    lo, hi = np.asarray(robot.q_lower, float)[J] - widen, np.asarray(robot.q_upper, float)[J] + widen
    objs_a = [o for o, li in zip(model.objects, model.object_link) if li == ia]
    objs_b = [o for o, li in zip(model.objects, model.object_link) if li == ib]
    verts = {link: np.concatenate([m.vertices for m in model.meshes[link]]) for link in (link_a, link_b)}

    def measure(center, need_apart: bool):
        q = np.zeros(robot.n_joints)
        q[J] = center
        T = model.set_configuration(q)
        d = min(fcl.distance(x, y, fcl.DistanceRequest(), fcl.DistanceResult()) for x in objs_a for y in objs_b)
        apart = False
        if need_apart:
            boxes = [verts[n] @ T[robot.link_index(n)][:3, :3].T + T[robot.link_index(n)][:3, 3] for n in (link_a, link_b)]
            apart = bool(np.any(boxes[0].max(0) < boxes[1].min(0)) or np.any(boxes[1].max(0) < boxes[0].min(0)))
        return float(d), apart

    cells = [((lo + hi) / 2, (hi - lo) / 2)]
    clearance, n_cells, nested_excluded = np.inf, 0, False
    while cells:
        c, h = cells.pop()
        n_cells += 1
        if progress and n_cells % 10_000 == 0:
            progress(f"{link_a}:{link_b}: {n_cells} cells, {len(cells)} open")
        if n_cells > max_cells:
            return dict(proven=False, why=f"more than {max_cells} cells", cells=n_cells, joints=J)
        d, apart = measure(c, not nested_excluded)
        nested_excluded |= apart
        if d <= FCL_TOLERANCE_M + target_m:
            return dict(proven=False, why=f"the meshes come within {d:.6f} m at {dict(zip(J, c.tolist()))}",
                        cells=n_cells, joints=J)
        bound = float(a_B @ h)
        if d - FCL_TOLERANCE_M - bound > target_m:
            clearance = min(clearance, d - FCL_TOLERANCE_M - bound)
            continue
        k = int(np.argmax(a_B * h))
        for s in (-0.5, 0.5):
            c2, h2 = c.copy(), h.copy()
            h2[k] /= 2
            c2[k] += s * h[k]
            cells.append((c2, h2))
    if not nested_excluded:
        return dict(proven=False, why="no configuration with disjoint bounding boxes (nesting not excluded)",
                    cells=n_cells, joints=J)
    return dict(proven=True, clearance_m=float(clearance), cells=n_cells, joints=J, lower=lo.tolist(),
                upper=hi.tolist())


def main(argv=None) -> int:
    import yaml

    from experiments.collision import CollisionModel
    from larc_jax.enclosure.robot_file import load_robot_file
    from larc_jax.io import atomic_write_text
    from larc_jax.leaf.self_collision import link_geometry_sha256

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--out", default=str(data_path(PIPER_SELF_SEPARATION)))
    args = p.parse_args(argv)
    robot, capsules = load_robot_file(None)
    model = CollisionModel(robot)
    pairs = []
    for a, b in DEFAULT_PAIRS:
        t0 = time.perf_counter()
        rec = prove_pair(model, capsules, a, b, progress=lambda msg: print(msg, flush=True))
        print(f"{a}:{b}: {rec} ({time.perf_counter() - t0:.1f} s)", flush=True)
        if rec["proven"]:
            pairs.append({"a": a, "b": b, "joints": {robot.active_joint_names[j]: [lo, hi] for j, lo, hi in
                                                     zip(rec["joints"], rec["lower"], rec["upper"])},
                          "clearance_m": math.floor(rec["clearance_m"] * 1e6 * (1 - 1e-9)) / 1e6, "cells": rec["cells"],
                          "geometry_sha256": {n: link_geometry_sha256(robot, n) for n in (a, b)}})
    doc = {"urdf_sha256": robot.urdf_sha256, "urdf": Path(robot.urdf_path).name,
           "method": "branch and bound over the joints between the links: FCL mesh distance at the cell centre "
                     f"minus sum_j a_Bj h_j minus {FCL_TOLERANCE_M} m (experiments/self_separation.py)",
           "pairs": pairs}
    header = ("# Link pairs proven never to touch over the whole joint range (written by\n"
              "# `python -m experiments.self_separation`; see that module for the proof).\n")
    atomic_write_text(args.out, header + yaml.safe_dump(doc, sort_keys=False, default_flow_style=None, width=120))
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
