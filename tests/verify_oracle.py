"""The fuzz test's oracle (``tests/test_verify_fuzz.py``): its own strict reading of a
certificate's claim (:func:`read_claim`, independent of ``larc_jax.products.verify``'s parsing), and two
ways to accept a claim: :func:`implied` by a claim known true (the original certificate's), or
:func:`claim_holds`, re-proved from the files it names with the NumPy leaf test."""

from __future__ import annotations

import dataclasses
import json
import math
import os
from pathlib import Path

import numpy as np

from larc_jax.enclosure.robot_file import load_robot_file
from larc_jax.errors import GeometryChanged, LarcInputError
from larc_jax.leaf.interval import trajectory_rounding
from larc_jax.leaf.reference import leaf_enclosures, leaf_test_np
from larc_jax.model.scene import read_scene
from larc_jax.leaf.self_collision import curve_ranges, load_separation, self_pairs
from larc_jax.model.trajectory_files import read_trajectory

_ROBOTS: dict = {}


def cached_robot_load(load, path=None, hold=None, active_joints=None):
    """``load(path, hold=..., active_joints=...)`` (:func:`load_robot_file`), served from a cache
    when the same file (same stamp) is loaded with the same arguments; a failure is not cached."""
    try:
        st = os.stat(path) if path is not None else None
        key = (str(path), st and (st.st_mtime_ns, st.st_size), tuple(sorted((hold or {}).items())),
               tuple(active_joints or ()))
        hash(key)
    except (TypeError, OSError, ValueError):
        return load(path, hold=hold, active_joints=active_joints)
    if key not in _ROBOTS:
        _ROBOTS[key] = load(path, hold=hold, active_joints=active_joints)
    return _ROBOTS[key]




class Unreadable(Exception):
    """The certificate is not what the format documents (so it makes no claim to accept)."""


def _hex(s, where) -> float:
    if not isinstance(s, str):
        raise Unreadable(f"{where}: not a string")
    try:
        x = float.fromhex(s)
    except (ValueError, OverflowError) as exc:
        raise Unreadable(f"{where}: {exc}") from None
    if not math.isfinite(x):
        raise Unreadable(f"{where}: not finite")
    return x


def _num(v, where) -> float:
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
        raise Unreadable(f"{where}: not a finite number")
    return float(v)


def _tolerance(v, active) -> dict | None:
    """The run spec's tracking tolerance as joint -> value (None: none): one number for every
    active joint, one per active joint, or a mapping."""
    if v is None:
        return None
    if isinstance(v, dict):
        out = {str(j): _num(x, f"tolerance {j}") for j, x in v.items()}
    elif isinstance(v, list):
        if len(v) != len(active):
            raise Unreadable("tolerance length")
        out = {j: _num(x, "tolerance") for j, x in zip(active, v)}
    else:
        out = {j: _num(v, "tolerance") for j in active}
    if out and min(out.values()) < 0:
        raise Unreadable("negative tolerance")
    return out


def _field(doc, key, kind, where):
    if not isinstance(doc, dict) or key not in doc:
        raise Unreadable(f"{where}.{key} missing")
    v = doc[key]
    if not isinstance(v, kind) or (isinstance(v, bool) and bool not in (kind if isinstance(kind, tuple) else (kind,))):
        raise Unreadable(f"{where}.{key}: {type(v).__name__}")
    return v


def _strs(v, where):
    if not isinstance(v, list) or not all(isinstance(x, str) for x in v):
        raise Unreadable(f"{where}: not a list of strings")
    return v


def _path(p) -> str | None:
    return None if p is None else str(Path(p).resolve())


@dataclasses.dataclass(frozen=True)
class TrajClaim:
    file: str
    sha256: str | None
    arrays_sha256: str
    velocities: str
    scene: tuple  # (file, sha256, arrays_sha256)
    leaves: tuple  # ((t0, t1), ...)


@dataclasses.dataclass(frozen=True)
class Claim:
    robot: tuple  # (file, sha256, urdf_sha256, geometry, active joints, capsules)
    stated: dict
    excluded: frozenset
    margin_m: float
    padding_m: float  # every mesh clears margin_m + padding_m
    enclosure: str
    tolerance: dict | None
    self_collision: tuple | None  # (margin_m, skipped pairs)
    trajectories: tuple
    swept: bool = False  # how the leaves are proven (the swept stage), not part of what is claimed


def _no_duplicates(pairs):
    keys = [k for k, _ in pairs]
    if len(set(keys)) != len(keys):
        raise Unreadable("duplicate JSON key")
    return dict(pairs)


def read_claim(text: str) -> Claim:
    """The claim of a certificate's text, read strictly from the fields the format documents and
    the checker reads (informational fields such as ``stage`` or ``held_joints`` are not part of
    the claim); a leading byte order mark is allowed, duplicate keys are not (NaN and Infinity
    parse, as ``json`` does, and are refused where a field is read: its type is checked)."""
    try:
        doc = json.loads(text.removeprefix("\ufeff"), object_pairs_hook=_no_duplicates)
    except (ValueError, RecursionError) as exc:
        raise Unreadable(f"not JSON: {exc}") from None
    if not isinstance(doc, dict) or doc.get("format") != "larc-certificate" or doc.get("version") != 4:
        raise Unreadable("format/version")
    p, r = _field(doc, "parameters", dict, ""), _field(doc, "robot", dict, "")
    margin = _num(_field(p, "margin_m", (int, float), "p"), "margin_m")
    depth = _field(p, "max_depth", int, "p")
    if margin <= 0 or not 0 <= depth <= 64 or _field(p, "dtype", str, "p") not in ("float64", "float32"):
        raise Unreadable("margin, depth or dtype")
    padding = _num(_field(p, "padding_m", (int, float), "p"), "padding_m")
    if not padding >= 0:
        raise Unreadable("padding")
    enclosure = _field(p, "enclosure", str, "p")
    if enclosure not in ("hull", "capsules"):
        raise Unreadable("enclosure")
    if _field(p, "velocities", str, "p") not in ("recorded", "finite-difference"):
        raise Unreadable("parameters.velocities")
    active = tuple(_strs(_field(r, "active_joints", list, "robot"), "active"))
    tol = _tolerance(_field(p, "tracking_tolerance", (int, float, list, dict, type(None)), "p"), active)
    sc = (_num(_field(p, "self_margin_m", (int, float), "p"), "self margin"),
          frozenset(_strs(_field(p, "self_skip", list, "p"), "skip")))
    sc = sc if _field(p, "self_collision", bool, "p") else None
    robot_file = _field(r, "file", (str, type(None)), "robot")
    stated = {j: _hex(v, f"stated {j}") for j, v in _field(r, "stated_joints", dict, "robot").items()}
    robot = (_path(robot_file) if robot_file is not None else None, _field(r, "sha256", str, "robot"),
             _field(r, "urdf_sha256", str, "robot"), json.dumps(_field(r, "geometry", dict, "robot"), sort_keys=True),
             tuple(_strs(_field(r, "active_joints", list, "robot"), "active")),
             tuple(_strs(_field(r, "capsules", list, "robot"), "capsules")))
    scenes = []
    for s in _field(doc, "scenes", list, ""):
        scenes.append((_path(_field(s, "file", str, "scene")), _field(s, "sha256", (str, type(None)), "scene"),
                       _field(s, "arrays_sha256", str, "scene")))
    trajs = []
    for t in _field(doc, "trajectories", list, ""):
        if not _field(t, "certified", bool, "traj"):
            continue
        lv = _field(t, "leaves", dict, "traj")
        t0, t1 = _field(lv, "t0", list, "leaves"), _field(lv, "t1", list, "leaves")
        if len(t0) != len(t1) or not t0:
            raise Unreadable("leaf columns")
        k = _field(t, "scene", int, "traj")
        if not 0 <= k < len(scenes):
            raise Unreadable("scene index")
        velocities = t.get("velocities")
        velocities = p["velocities"] if velocities is None else velocities
        if velocities not in ("recorded", "finite-difference"):
            raise Unreadable(f"velocities {velocities!r}")
        trajs.append(TrajClaim(_path(_field(t, "file", str, "traj")), _field(t, "sha256", (str, type(None)), "traj"),
                               _field(t, "arrays_sha256", str, "traj"), velocities, scenes[k],
                               tuple((_hex(a, "t0"), _hex(b, "t1")) for a, b in zip(t0, t1))))
    swept = p.get("swept", False)
    if not isinstance(swept, bool):
        raise Unreadable("swept")
    return Claim(robot, stated, frozenset(_strs(_field(p, "ignore_links", list, "p"), "excluded")), margin, padding,
                 enclosure, tol, sc, tuple(trajs), swept)


def implied(m: Claim, o: Claim) -> bool:
    """Does the original claim ``o`` (true) imply ``m``: the same robot, files and hashes (a file
    hash may be dropped), at most as strong assumptions, and trajectories the original certified,
    with the same leaf cover (its proof)."""
    def weaker_or_equal(mine: dict | None, orig: dict | None) -> bool:
        mine, orig = mine or {}, orig or {}
        return all(v <= orig.get(j, 0.0) for j, v in mine.items())

    def same_traj(a: TrajClaim, b: TrajClaim) -> bool:
        def what(t):
            return t.file, t.arrays_sha256, t.velocities, t.scene[0], t.scene[2], t.leaves

        return what(a) == what(b) and a.sha256 in (b.sha256, None) and a.scene[1] in (b.scene[1], None)

    return (m.robot == o.robot and m.excluded >= o.excluded and m.margin_m <= o.margin_m
            and m.padding_m <= o.padding_m
            and all(j in m.stated and m.stated[j] == v for j, v in o.stated.items())
            and weaker_or_equal(m.tolerance, o.tolerance)
            and (m.self_collision is None or (o.self_collision is not None and m.self_collision[0] <=
                                              o.self_collision[0] and m.self_collision[1] >= o.self_collision[1]))
            and all(any(same_traj(t, u) for u in o.trajectories) for t in m.trajectories))


def claim_holds(c: Claim) -> str | None:
    """Re-prove the claim from the files it names with the NumPy leaf test: None if it holds,
    else why not. Each claimed trajectory's leaves must cover its horizon end to end."""
    try:
        robot, caps = cached_robot_load(load_robot_file, c.robot[0], hold=c.stated, active_joints=list(c.robot[4]))
        more = [x for x in c.excluded if x not in caps.excluded_links]
        caps = caps.without_links(robot, more) if more else caps
        caps = caps.with_padding(c.padding_m)  # the claim: every mesh clears margin + padding
        delta = None if c.tolerance is None else np.array([c.tolerance.get(j, 0.0) for j in robot.active_joint_names])
        enc = leaf_enclosures(robot, caps, c.enclosure, delta, swept=c.swept)
        pairs = None
        if c.self_collision is not None:
            pairs = self_pairs(robot, caps, c.self_collision[0], sorted(c.self_collision[1]),
                               proven=load_separation(robot))
            pairs = pairs if pairs.n_pairs else None
        for t in c.trajectories:
            scene = read_scene(t.scene[0], frame=robot.link_names[0])
            traj = read_trajectory(t.file, robot, velocities=t.velocities)
            ends = [float(traj.t[0])] + [b for _, b in t.leaves]
            if [a for a, _ in t.leaves] != ends[:-1] or ends[-1] != float(traj.t[-1]) or \
                    any(not a < b for a, b in t.leaves):
                return f"{t.file}: the leaves do not cover the horizon"
            bounds = trajectory_rounding(traj, robot, enc.capsules, np.float64, enc.hulls)
            skip = pairs.skip_mask(*curve_ranges(traj, delta)) if pairs is not None else None
            for a, b in t.leaves:
                g, guard, *_, stage = leaf_test_np(robot, enc, traj, scene, a, b, c.margin_m, bounds, pairs, skip)
                if not (stage > 0 and g > guard):
                    return f"{t.file}: leaf [{a!r}, {b!r}] fails (g {g!r}, guard {guard!r})"
    except (LarcInputError, GeometryChanged) as exc:
        return f"cannot read a file it names: {exc}"
    return None
