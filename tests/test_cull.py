"""Culling the pieces of large scenes (larc_jax.engine.cull): clusters hold their pieces, a node
drops only what it proved clear, and a culled run decides every leaf as every pair does, records
a clearance never above every pair's (equal where it is within CULL_SLACK_M of the guard),
verifies, and still clears the margin at the boundary (FCL)."""

from __future__ import annotations

import dataclasses
import shutil
from pathlib import Path

import numpy as np
import pytest

from larc_jax.engine import cull as cull_module
from larc_jax.engine.cull import CULL_SLACK_M, CullPart, build_cull, piece_clusters
from larc_jax.leaf.record import LeafRecord
from larc_jax.model.point_sets import PointSets, convex_pieces
from larc_jax.model.scene import Scene, read_scene
from tests.capsule_audit import bracket_fcl, capsule_clearance, last_certified, point_clearance

EX = Path(__file__).resolve().parent.parent / "configs" / "examples"
SAME = ["id", "depth", "index", "t0", "t1", "certified", "stage", "other_capsule"]


def _cloud_scene(points, radius=0.0, boxes=0) -> Scene:
    pieces = convex_pieces(points, None, 64)
    lo = np.array([[0.3, 0.3, 0.3]] * boxes).reshape(-1, 3)
    return Scene(lo=lo, hi=lo + 0.05, point_sets=PointSets(
        kinds=("points",), names=("cloud",), files=("",), file_sha256=("",), radius=(radius,),
        pieces=tuple(pieces), owner=(0,) * len(pieces)))


def test_clusters_hold_their_pieces():
    rng = np.random.default_rng(0)
    scene = _cloud_scene(rng.uniform(-0.5, 0.5, (5000, 3)), radius=0.004, boxes=2)
    members, lo, hi = piece_clusters(scene, 8)
    first = 2  # two boxes come first
    flat = np.sort(np.concatenate(members))
    assert (flat == np.arange(first, first + len(scene.point_sets.pieces))).all()  # each piece once
    assert max(len(m) for m in members) <= 8 and len(members) >= len(scene.point_sets.pieces) / 8
    for m, a, b in zip(members, lo, hi):
        for item in m:
            v = scene.point_sets.pieces[item - first]
            assert (v - 0.004 >= a).all() and (v + 0.004 <= b).all()  # the points grown by their radius


def test_a_node_drops_only_clusters_proven_clear_and_floors_the_least(monkeypatch):
    pts = np.array([[0.0, 0, 0], [1.0, 0, 0], [2.0, 0, 0], [3.0, 0, 0]])
    scene = Scene(lo=np.zeros((0, 3)), hi=np.zeros((0, 3)), point_sets=PointSets(
        kinds=("points",), names=("c",), files=("",), file_sha256=("",), radius=(0.0,),
        pieces=tuple(p[None] for p in pts), owner=(0,) * 4))
    monkeypatch.setattr(cull_module, "CLUSTER_PIECES", 1)
    D = cull_module.CULL_DEPTH
    n_nodes = (1 << (D + 1)) - 1
    tau = CULL_SLACK_M
    slack = np.tile([tau * 0.5, tau * 3, np.nan, tau * 2], (n_nodes, 1))
    slack[1] = [tau * 3, tau * 3, np.nan, tau * 3]  # node (1, 0) drops clusters 0 and 3 too
    slack[3] = [tau * 0.1, tau * 0.1, tau * 9, tau * 0.1]  # (2, 0): below (1, 0); drops 2, keeps nothing else
    slack[2] = [tau * 3, tau * 3, tau * 3, tau * 3]  # (1, 1): drops everything; its subtree is never tested
    finite = np.ones(n_nodes, bool)
    finite[4] = False  # (2, 1): a non-finite placement drops nothing
    cap = np.tile([0, 1, 2, 3], (n_nodes, 1))
    asked = []

    def run(kernel, boxes, traj, depth, index, width):
        assert width == 4 and (traj == 0).all() and boxes.mask.shape == (1, 4)
        node = (1 << depth) - 1 + index
        asked.extend(node.tolist())
        return slack[node], slack[node] + 1e-9, np.full((len(node), 4), 1e-9), cap[node], finite[node]

    c = build_cull([scene], np.array([0]), n_items=5, dtype=np.float64, run=run)
    item = [int(m[0]) for m in c.members[0]]  # the item of each cluster

    def kept(node):
        return {item[k] for k in np.flatnonzero(c.keep[0, node])}

    assert kept(0) == {0, 2}  # NaN is kept; above CULL_SLACK_M dropped
    assert c.floor.box[0, 0] == 3 and c.floor.capsule[0, 0] == 3  # the least dropped slack
    assert c.floor.clearance_m[0, 0] == pytest.approx(tau * 2 + 1e-9)
    assert kept(1) == {2} and c.floor.clearance_m[0, 1] == pytest.approx(tau * 2 + 1e-9)  # the parent's floor is lower
    assert kept(3) == set() and c.floor.box[0, 3] == 3  # (2, 0) dropped cluster 2 at 9 tau: the floor stays
    assert kept(4) == {2}  # (2, 1): non-finite, keeps what its parent kept
    assert kept(2) == set() and c.floor.clearance_m[0, 2] == pytest.approx(tau * 2 + 1e-9)
    below = [(1 << d) - 1 + i for d in range(2, D + 1) for i in range(1 << d) if i >> (d - 1) == 1]
    assert not set(below) & set(asked) and not c.keep[0, below].any()  # never tested, nothing kept
    assert (c.floor.clearance_m[0, below] == c.floor.clearance_m[0, 2]).all()
    # intervals below depth CULL_DEPTH use their ancestor's node
    assert (c.node(np.array([0, 1, D, D + 3]), np.array([0, 1, 5, 5 << 3 | 7])) == [0, 2, (1 << D) - 1 + 5,
                                                                                     (1 << D) - 1 + 5]).all()


def test_finish_maps_items_and_takes_the_floor_only_where_lower():
    items = np.array([[7, 3, 9, 9], [4, 9, 9, 9], [2, 5, 9, 9], [9, 9, 9, 9]])
    floor = LeafRecord(np.array([0.5, 0.05, 0.5, 0.2]), np.zeros(4), np.array([1, 1, 1, 1]), np.array([6, 6, 6, 6]),
                       np.full(4, -1), np.zeros(4, np.int8))
    part = CullPart(np.arange(4), (np.zeros(4, int), items), floor)
    rec = LeafRecord(np.array([0.1, 0.1, -0.1, np.inf]), np.zeros(4), np.array([2, 2, 2, 0]), np.array([1, 0, 1, 0]),
                     np.full(4, -1), np.array([1, 1, 0, 1], np.int8))
    out = part.finish(rec)
    assert out.box.tolist() == [3, 6, 5, 6]  # mapped; the floor where it is lower on a passed leaf
    assert out.clearance_m.tolist() == [0.1, 0.05, -0.1, 0.2] and out.capsule.tolist() == [2, 1, 2, 1]
    assert out.stage.tolist() == [1, 1, 0, 1]  # a failed leaf keeps its own record
    # a node that kept nothing: no item list, the floor is the record
    empty = CullPart(np.arange(4), (np.zeros(4, int), np.zeros((4, 0), int)), floor)
    none = LeafRecord(np.full(4, np.inf), np.zeros(4), np.zeros(4, int), np.zeros(4, int), np.full(4, -1),
                      np.ones(4, np.int8))
    out = empty.finish(none)
    assert out.clearance_m.tolist() == floor.clearance_m.tolist() and out.box.tolist() == [6] * 4


def test_item_margins_is_the_reference_per_item(robot, capsules):
    """The per-item capsule test (engine.kernels.item_margins, what a node's clusters and a leaf's
    narrowed later stages read) against the NumPy float64 reference: every item's least
    ``g - guard`` over the capsules, that pair's g, guard and capsule, on random intervals of the
    camera cell (mesh + cloud) and the shapes cell (boxes + posed shapes); a padding item is clear."""
    import jax

    from larc_jax.engine import batch as B
    from larc_jax.engine.kernels import item_margins
    from larc_jax.leaf.interval import evaluate_interval_np, trajectory_rounding
    from larc_jax.model.trajectory_files import read_trajectory

    rng = np.random.default_rng(11)
    traj = read_trajectory(EX / "reach_left.yaml", robot)
    bounds = trajectory_rounding(traj, robot, capsules)
    guard = np.asarray(bounds.guard_m, np.float64)
    for scene in (_camera(), read_scene(EX / "cell_shapes.yaml")):
        b = B.prepare([traj], [scene], robot, capsules, 0.01, np.float64, [bounds], devices=None)
        n = 8
        tr = np.zeros(n, np.int64)
        depth = rng.integers(0, 9, n)
        index = np.array([rng.integers(0, 2**d) for d in depth])
        t0, t1 = b.endpoints(tr, depth, index)
        with jax.enable_x64(True):
            slack, g, grd, cap, finite = (np.asarray(x) for x in item_margins(*b.kernel_args(tr, t0, t1)))
        m = scene.n_obstacles
        assert finite.all() and (slack[:, m:] == np.inf).all()  # only the batch's padding item beyond
        for i in range(n):
            ev = evaluate_interval_np(robot, capsules, traj, scene, float(t0[i]), float(t1[i]), 0.01, bounds)
            ref = ev.g_pairs - guard[:, None]  # (C, items)
            c = ref.argmin(axis=0)
            np.testing.assert_allclose(slack[i, :m], ref.min(axis=0), rtol=0, atol=1e-12)
            np.testing.assert_allclose(g[i, :m], ev.g_pairs[c, np.arange(m)], rtol=0, atol=1e-12)
            np.testing.assert_array_equal(grd[i, :m], guard[c])
            assert (cap[i, :m] == c).all()


TOWARD = -np.array([-0.275, 0.325, 0.0]) / np.linalg.norm([-0.275, 0.325])
"""From the camera cell's bracket toward the arm's base."""


def _moved(scene: Scene, s: float) -> Scene:
    """The camera cell's pieces moved by ``s`` m toward the arm's base."""
    ps = scene.point_sets
    return Scene(lo=np.zeros((0, 3)), hi=np.zeros((0, 3)), point_sets=PointSets(
        kinds=ps.kinds, names=ps.names, files=ps.files, file_sha256=ps.file_sha256, radius=ps.radius,
        pieces=tuple(p + s * TOWARD for p in ps.pieces), owner=ps.owner))


def _camera(tmp_path=None):
    if tmp_path is None:
        return read_scene(EX / "cell_camera.yaml")
    for name in ("cell_camera.yaml", "bracket.stl", "table_cloud.npy"):
        shutil.copy(EX / name, tmp_path / name)
    return read_scene(tmp_path / "cell_camera.yaml")


@pytest.fixture
def culled(monkeypatch):
    """Cull scenes of 16 pieces or more, in clusters of 4 (the camera cell's 67 pieces: 17 clusters)."""
    built = []
    original = cull_module.build_cull

    def spy(*args, **kwargs):
        built.append(original(*args, **kwargs))
        return built[-1]

    monkeypatch.setattr(cull_module, "CULL_MIN_PIECES", 16)
    monkeypatch.setattr(cull_module, "CLUSTER_PIECES", 4)
    import larc_jax.engine.batch as batch_module

    monkeypatch.setattr(batch_module, "build_cull", spy)
    return built


def _compare(robot, capsules, trajs, scene, built, monkeypatch, **kw):
    import larc_jax as lj
    import larc_jax.engine.batch as batch_module

    res = lj.certify(trajs, [scene] * len(trajs), robot, capsules, **kw)
    assert built and (~built[-1].keep).any(), "nothing was culled"
    with monkeypatch.context() as m:
        m.setattr(batch_module, "worth_culling", lambda scenes: False)
        full = lj.certify(trajs, [scene] * len(trajs), robot, capsules, **kw)
    a, b = res.leaves_dataframe(), full.leaves_dataframe()
    for col in SAME:
        assert (a[col].astype(str) == b[col].astype(str)).all(), col
    g, g_full, guard = a.clearance_m.to_numpy(), b.clearance_m.to_numpy(), b.guard_m.to_numpy()
    assert (g <= g_full + 1e-12).all()  # never above every pair's
    near = g_full - guard <= CULL_SLACK_M - 1e-6
    assert (np.abs(g[near] - g_full[near]) <= 1e-12).all()  # every pair's where it matters
    assert (a.box[near] == b.box[near]).all() and (a.capsule[near] == b.capsule[near]).all()
    names = set(b.box) | {f"{n}[{g}]" for n, m in zip(scene.point_sets.names, range(99)) for g in range(999)}
    assert set(a.box) <= names, set(a.box) - names  # every recorded item is one of the scene's
    assert (res.certified == full.certified).all()
    return res, a, b


@pytest.mark.slow
def test_culled_runs_decide_as_every_pair(robot, capsules, culled, monkeypatch):
    from larc_jax.model.trajectory_files import read_trajectory

    scene = _camera()
    trajs = [read_trajectory(EX / n, robot) for n in ("reach_left.yaml", "sweep_front.yaml")]
    # The table's cloud alone (with the bracket, the base's capsule, which never moves, is 16 mm
    # from it at every leaf): every leaf clears by more than CULL_SLACK_M and some record floors.
    ps = scene.point_sets
    table = [g for g, o in enumerate(ps.owner) if ps.kinds[o] == "points"]
    cloud = Scene(lo=np.zeros((0, 3)), hi=np.zeros((0, 3)), point_sets=dataclasses.replace(
        ps, pieces=tuple(ps.pieces[g] for g in table), owner=tuple(ps.owner[g] for g in table)))
    _, a, b = _compare(robot, capsules, trajs, cloud, culled, monkeypatch, method="fine", max_depth=7,
                       enclosure="capsules")
    assert (a.clearance_m.to_numpy() < b.clearance_m.to_numpy()).any()  # some leaf records its node's floor
    _compare(robot, capsules, trajs, scene, culled, monkeypatch, method="larc", enclosure="capsules")


@pytest.mark.slow
def test_culled_larc_cascade_certifies_as_every_pair_and_verifies(robot, capsules, culled, monkeypatch, tmp_path):
    """LARC with the cascade in a culled batch: the same trajectories certified as every pair;
    an interval above the deepest level that meets more than the widest list is bisected,
    untested above the culled depth and rather than sent to the hull stage below it (so the
    leaves may be finer), and every leaf verifies with the NumPy reference."""
    import larc_jax as lj
    import larc_jax.engine.batch as batch_module
    from larc_jax.model.trajectory_files import read_trajectory

    scene = _camera(tmp_path)
    names = ("reach_left.yaml", "sweep_front.yaml")
    trajs = [read_trajectory(EX / n, robot) for n in names]
    deferred, untested = [], []
    stages = batch_module.Batch._stages

    def spy(self, traj, a, b, sel, on_chunk, on_compile, cascade, may_bisect=None, shallow=None):
        record, self_test = stages(self, traj, a, b, sel, on_chunk, on_compile, cascade, may_bisect, shallow)
        if may_bisect is not None and len(sel) == 1 and self.cull is not None:  # wider than the widest list
            deferred.append(int((may_bisect & (record.stage == 0)).sum()))
            # above the culled depth, failed without a test (NaN); below it, tested (never NaN here)
            assert (np.isnan(record.clearance_m) == (may_bisect & shallow)).all()
            untested.append(int((may_bisect & shallow).sum()))
        return record, self_test

    monkeypatch.setattr(batch_module.Batch, "_stages", spy)
    res = lj.certify(trajs, [scene] * 2, robot, capsules, method="larc", enclosure="hull")
    with monkeypatch.context() as m:
        m.setattr(batch_module, "worth_culling", lambda scenes: False)
        full = lj.certify(trajs, [scene] * 2, robot, capsules, method="larc", enclosure="hull")
    assert culled and deferred and sum(deferred) > 0 and sum(untested) > 0  # some wide interval was bisected instead
    assert (res.certified == full.certified).all() and res.certified.any()
    assert res.evaluations.sum() >= full.evaluations.sum()
    path = tmp_path / "cert.json"
    lj.write_certificate(path, res, trajs, [scene] * 2, robot, capsules, trajectory_files=[EX / n for n in names],
                         scene_files=[tmp_path / "cell_camera.yaml"])
    assert lj.verify_certificate(path).checked == int(res.certified.sum())


@pytest.mark.slow
def test_a_culled_certificate_verifies(robot, capsules, culled, tmp_path):
    """A certificate of a culled run over the camera cell's cloud alone verifies, floors included
    (stored clearances below the recomputed ones are accepted; one above is refuted)."""
    import json

    from larc_jax import certify, verify_certificate, write_certificate
    from larc_jax.products.certificate import hexf, unhexf
    from larc_jax.model.trajectory_files import read_trajectory
    from larc_jax.products.verify import Refuted

    shutil.copy(EX / "table_cloud.npy", tmp_path / "table_cloud.npy")
    shutil.copy(EX / "reach_left.yaml", tmp_path / "reach_left.yaml")
    (tmp_path / "cloud.yaml").write_text(
        "frame: base_link\nobstacles:\n  - {name: table, type: points, file: table_cloud.npy, radius: 0.002}\n")
    scene, traj = read_scene(tmp_path / "cloud.yaml"), read_trajectory(tmp_path / "reach_left.yaml")
    res = certify(traj, scene, robot, capsules, method="fine", max_depth=6)
    assert res[0].certified and culled
    path = tmp_path / "cert.json"
    write_certificate(path, res, [traj], [scene], robot, capsules, trajectory_files=[tmp_path / "reach_left.yaml"],
                      scene_files=[tmp_path / "cloud.yaml"])
    report = verify_certificate(path)
    assert report.max_clearance_diff_m > 1e-6  # a floor was stored below the recomputed clearance, and accepted
    doc = json.loads(path.read_text())
    g = doc["trajectories"][0]["leaves"]["clearance_m"]
    g[3] = hexf(unhexf(g[3]) + 0.5)
    path.write_text(json.dumps(doc))
    with pytest.raises(Refuted, match="exceeds the recomputed"):
        verify_certificate(path)


@pytest.mark.slow
def test_the_boundary_with_culling_still_clears_the_margin(robot, capsules, monkeypatch):
    """The camera cell's cloud and bracket, slid toward the arm until the culled certification
    flips (every piece its own cluster, culled from 1 piece): FCL's clearance of the capsules from
    the moved bracket and the points at the last certified position exceeds the margin."""
    from larc_jax import certify
    from larc_jax.defaults import DEFAULT_MARGIN_M
    from larc_jax.model.trajectory_files import read_trajectory

    monkeypatch.setattr(cull_module, "CULL_MIN_PIECES", 1)
    monkeypatch.setattr(cull_module, "CLUSTER_PIECES", 1)
    traj = read_trajectory(EX / "reach_left.yaml")
    full = _camera()
    ps = full.point_sets

    def ok(s):
        return certify(traj, _moved(full, s), robot, capsules, method="larc", enclosure="capsules")[0].certified

    lo = last_certified(ok, 0.0, 0.1, 8)
    to_mesh = capsule_clearance(robot, capsules, traj, [bracket_fcl(EX, lo * TOWARD)], n=150)
    cloud = np.concatenate([p for p, o in zip(_moved(full, lo).point_sets.pieces, ps.owner) if ps.kinds[o] == "points"])
    radius = max(r for r, k in zip(ps.radius, ps.kinds) if k == "points")
    to_points = point_clearance(robot, capsules, traj, cloud, 150) - radius
    assert min(to_mesh, to_points) > DEFAULT_MARGIN_M
    assert min(to_mesh, to_points) - DEFAULT_MARGIN_M < 0.03  # the motion bound's slack, not a vacuous pass
