"""The checker proves the enclosures it relies on (issue 18, forgery 1).

A robot file whose capsules are shrunk to 1 um and moved 5 m below their links, with
``padding_m: 0`` and the real PIPER URDF, hashes correctly and gives a certificate whose leaves
the checker's own NumPy leaf test passes, for a trajectory that drives through the post: only
the containment proof refutes it. Also: the hull-part proof is one-sided (a point is never
claimed inside a part it is outside of), a shrunk hull part or stated-finger capsule is refuted
by ``verify`` and ``verify-capsules``, and the shipped file's enclosures are proven.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import yaml

import larc_jax.products.verify as verify_mod
from larc_jax.drivers.cli import EXIT_BAD_INPUT, EXIT_OK, EXIT_REFUTED, main
from larc_jax.enclosure import proof
from larc_jax.enclosure.hull import hull_model
from larc_jax.enclosure.proof import EnclosureNotProven, HullPartTest, prove_enclosures
from larc_jax.enclosure.robot_file import default_capsule_path, load_robot_file
from larc_jax.products.verify import Refuted, verify_certificate

ROOT = Path(__file__).resolve().parent.parent
EX = ROOT / "configs" / "examples"
REACH, SWEEP, CELL = (str(EX / n) for n in ("reach_left.yaml", "sweep_front.yaml", "cell.yaml"))


def _robot_file(tmp_path, piper_dir, name: str, edit) -> Path:
    """The shipped robot file with the real URDF named, edited by ``edit(doc)``."""
    doc = yaml.safe_load(default_capsule_path().read_text())
    doc = {"urdf": str(piper_dir / "urdf" / "piper_description.urdf"),
           "package_dirs": {"piper_description": str(piper_dir)}, **doc}
    edit(doc)
    path = tmp_path / name
    path.write_text(yaml.safe_dump(doc, sort_keys=False))
    return path


def _shrink_all(doc) -> None:
    """Forgery 1: every capsule 1 um thick and 5 m below its link, no padding."""
    doc["padding_m"] = 0
    for cap in doc["capsules"] + doc.get("stated_capsules", []):
        cap["a"] = [cap["a"][0], cap["a"][1], cap["a"][2] - 5.0]
        cap["b"] = [cap["b"][0], cap["b"][1], cap["b"][2] - 5.0]
        cap["radius"] = 1e-6


def _certificate(tmp_path, robot_file: Path, trajectory: str) -> Path:
    """A certificate made by the library with ``robot_file`` (NumPy reference scheduler: every
    leaf is the checker's own test), every hash consistent with the files."""
    import larc_jax as lj

    robot, capsules = load_robot_file(robot_file)
    traj = lj.read_trajectory(trajectory, robot)
    scene = lj.read_scene(CELL)
    result = lj.certify([traj], scene, robot, capsules, max_depth=6, method="reference")
    assert result.certified[0]
    return lj.write_certificate(tmp_path / f"{robot_file.stem}.json", result, [traj], scene, robot, capsules,
                                robot_file=str(robot_file), trajectory_files=[trajectory], scene_files=[CELL])


@pytest.fixture(scope="module")
def forged(tmp_path_factory, piper_dir):
    tmp = tmp_path_factory.mktemp("forged")
    evil = _robot_file(tmp, piper_dir, "evil.yaml", _shrink_all)
    return evil, _certificate(tmp, evil, SWEEP)


def test_shrunken_robot_file_is_refuted(forged, monkeypatch, capsys):
    evil, cert = forged
    doc = json.loads(cert.read_text())
    assert doc["trajectories"][0]["certified"] is True and doc["robot"]["file"] == str(evil)
    with pytest.raises(Refuted, match=r"link 'base_link' element \d+ \(collision 0: mesh .*base_link.STL triangle "
                                      r"\d+\) is not inside any of its capsules \('base_link'\).* vertex"):
        verify_certificate(cert)
    assert main(["verify", str(cert)]) == EXIT_REFUTED
    assert main(["verify", str(cert), "--trajectory", SWEEP, "--scene", CELL, "--robot", str(evil)]) == EXIT_REFUTED
    err = capsys.readouterr().err
    assert "REFUTED" in err and "link 'base_link'" in err and "evil.yaml" in err
    # Only the proof stands in the way: without it every hash and leaf of the forgery checks out.
    monkeypatch.setattr(verify_mod, "prove_enclosures",
                        lambda robot, capsules, hull, **kw: hull_model(robot, capsules.hull_parts, capsules.padding_m))
    assert verify_certificate(cert).checked == 1


def test_shipped_file_is_proven(robot, capsules):
    assert prove_enclosures(robot, capsules, True) is not None  # capsules and hull parts
    held, stated = load_robot_file(None, hold={"joint7": -0.01, "joint8": 0.01})
    assert prove_enclosures(held, stated, False) is None  # the stated-finger capsules


def test_stated_finger_capsule_is_proven(tmp_path, piper_dir):
    def shrink_link7(doc):
        doc["stated_capsules"][0]["radius"] = round(doc["stated_capsules"][0]["radius"] - 0.004, 6)

    path = _robot_file(tmp_path, piper_dir, "thin_finger.yaml", shrink_link7)
    robot, capsules = load_robot_file(path)
    prove_enclosures(robot, capsules, False)  # the stroke capsules are untouched
    robot, capsules = load_robot_file(path, hold={"joint7": 0.0, "joint8": 0.0})
    with pytest.raises(EnclosureNotProven, match=r"link 'link7' element .* capsules \('link7'\)"):
        prove_enclosures(robot, capsules, False)


def _shrunk_hull_model(link: str, factor: float = 0.97):
    """``hull_model`` with the first part of ``link`` shrunk towards its centroid (a faulty build)."""
    def build(robot, planes=(), padding_m=0.001):
        model = hull_model(robot, planes, padding_m)
        p = model.link_names.index(link)
        V = np.array(model.vertices)
        V[p] = V[p].mean(axis=0) + factor * (V[p] - V[p].mean(axis=0))
        import dataclasses

        return dataclasses.replace(model, vertices=V)
    return build


@pytest.fixture(scope="module")
def honest(tmp_path_factory, piper_dir):
    """A true certificate (reach_left, the hull cascade) with a robot file that leaves out its base."""
    tmp = tmp_path_factory.mktemp("honest")
    path = _robot_file(tmp, piper_dir, "no_base.yaml", lambda doc: doc.update(ignored_links=["base_link"]))
    cert = _certificate(tmp, path, REACH)
    assert verify_certificate(cert).checked == 1
    return path, cert


def test_shrunk_hull_part_is_refuted(honest, monkeypatch, capsys):
    plain, cert = honest
    monkeypatch.setattr(proof, "hull_model", _shrunk_hull_model("link6"))
    with pytest.raises(Refuted, match=r"link 'link6' element .* not inside any of its hull parts \(7 'link6'\)"):
        verify_certificate(cert)
    assert main(["verify-capsules", str(plain)]) == EXIT_BAD_INPUT
    assert "link 'link6'" in capsys.readouterr().err


def test_hull_part_proof_is_one_sided():
    """A point is claimed inside conv(V) + B(0, r) only when it is (a box: exact distances)."""
    rng = np.random.default_rng(7)
    lo, hi = np.array([-0.03, 0.01, 0.2]), np.array([0.05, 0.04, 0.31])
    V = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
    pts = np.concatenate([rng.uniform(lo - 0.01, hi + 0.01, (4000, 3)),
                          np.where(rng.random((2000, 3)) < 0.5, lo, hi) * (1 + rng.choice([-1, 1], (2000, 3)) * 1e-13),
                          np.clip(rng.uniform(lo - 1e-12, hi + 1e-12, (2000, 3)), lo - 1e-12, hi + 1e-12), V])
    true = np.linalg.norm(np.maximum(np.maximum(lo - pts, pts - hi), 0.0), axis=1)
    for r in (0.0, 1e-12, 1e-6, 0.004):
        inside = HullPartTest(V, r).contains(pts)
        assert not np.any(inside & (true > r)), r
        assert inside[-8:].all()  # the corners themselves
        assert inside[:4000][true[:4000] < r - 1e-9].all() or r < 1e-9  # everything clearly inside is proven
    deep = rng.uniform(lo + 1e-6, hi - 1e-6, (500, 3))
    assert HullPartTest(V, 0.0).contains(deep).all()  # strictly inside: no radius needed


def test_recorded_robot_assumptions_are_checked(honest, tmp_path):
    """The certificate's record of held joints and left-out links must be what the files give."""
    _, cert = honest
    doc = json.loads(cert.read_text())
    assert doc["parameters"]["ignore_links"] == ["base_link"]
    for edit, match in ((lambda d: d["parameters"].update(ignore_links=[]), "left out"),
                        (lambda d: d["robot"]["held_joints"].update(joint7=float.hex(-0.02)), "held joint values")):
        bad = json.loads(cert.read_text())
        edit(bad)
        path = tmp_path / "edited.json"
        path.write_text(json.dumps(bad))
        with pytest.raises(Refuted, match=match):
            verify_certificate(path)
