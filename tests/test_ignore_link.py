"""Links left out of the certificate: a fixed base standing on its table (``--ignore-link``, the
robot file's ``ignored_links``, ``CapsuleModel.without_links``)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import yaml

from larc_jax.drivers import cli
from larc_jax.errors import LarcInputError

EXAMPLES = Path(__file__).resolve().parent.parent / "configs" / "examples"
REACH = str(EXAMPLES / "reach_left.yaml")
TABLE = """frame: base_link
boxes:
  - {name: table, min: [-0.6, -0.6, -0.05], max: [0.6, 0.6, 0.0]}
"""


def larc(capsys, *args):
    capsys.readouterr()
    rc = cli.main([str(a) for a in args])
    out, err = capsys.readouterr()
    return rc, out, err


def test_without_links_drops_only_those_capsules(robot, capsules):
    fewer = capsules.without_links(robot, ["base_link"])
    keep = [c for c, link in enumerate(capsules.link_names) if link != "base_link"]
    assert fewer.excluded_links == ("base_link",) and "base_link" not in fewer.link_names
    assert fewer.names == tuple(capsules.names[c] for c in keep)
    for field in ("p_link_a", "p_link_b", "radius", "motion_a"):
        np.testing.assert_array_equal(np.asarray(getattr(fewer, field)), np.asarray(getattr(capsules, field))[keep])
    assert capsules.without_links(robot, []) is capsules


@pytest.mark.parametrize("links,needle", [
    (["link1"], "joint1"),          # turns with joint1: it moves
    (["link6"], "moves"),
    (["gripper"], "not a link"),
    (["link2", "base_link"], "moves"),
])
def test_without_links_refuses_moving_or_unknown_links(robot, capsules, links, needle):
    with pytest.raises(LarcInputError, match=needle):
        capsules.without_links(robot, links, what="--ignore-link")


def test_without_links_refuses_a_link_without_capsule_and_an_empty_model(robot, capsules):
    import dataclasses

    fewer = capsules.without_links(robot, ["base_link"])
    with pytest.raises(LarcInputError, match="no capsule"):
        fewer.without_links(robot, ["base_link"])
    c = capsules.link_names.index("base_link")
    base_only = dataclasses.replace(
        capsules, p_link_a=np.asarray(capsules.p_link_a)[[c]], p_link_b=np.asarray(capsules.p_link_b)[[c]],
        radius=np.asarray(capsules.radius)[[c]], motion_a=np.asarray(capsules.motion_a)[[c]],
        names=(capsules.names[c],), link_names=("base_link",), link_index=(capsules.link_index[c],))
    with pytest.raises(LarcInputError, match="leaves no capsule"):
        base_only.without_links(robot, ["base_link"])


def test_table_under_the_base(tmp_path, capsys):
    """Flush with the base, a table blocks every trajectory; leaving the base out certifies it,
    and the table and the JSON say the certificate excludes the base."""
    (tmp_path / "table.yaml").write_text(TABLE)
    rc, out, _ = larc(capsys, "certify", REACH, "--scene", tmp_path / "table.yaml", "--max-depth", "3")
    assert rc == 1 and "base_link / table" in out
    rc, out, _ = larc(capsys, "certify", REACH, "--scene", tmp_path / "table.yaml", "--ignore-link", "base_link",
                      "--json", tmp_path / "r.json")
    assert rc == 0 and "excludes links: base_link" in out
    doc = json.loads((tmp_path / "r.json").read_text())
    assert doc["excluded_links"] == ["base_link"] and doc["trajectories"][0]["certified"]
    assert doc["compile_time_s"] <= doc["wall_time_s"]


def test_ignore_link_refuses_a_moving_link(tmp_path, capsys):
    (tmp_path / "table.yaml").write_text(TABLE)
    rc, out, err = larc(capsys, "certify", REACH, "--scene", tmp_path / "table.yaml", "--ignore-link", "link3")
    assert rc == 2 and out == ""
    assert err.strip().splitlines() == [err.strip()] and "--ignore-link link3" in err and "moves" in err


def test_robot_file_field_ignored_links(tmp_path, capsys, piper_dir):
    from larc_jax.enclosure import default_capsule_path

    (tmp_path / "table.yaml").write_text(TABLE)
    doc = yaml.safe_load(default_capsule_path().read_text())
    doc = {"urdf": str(piper_dir / "urdf" / "piper_description.urdf"), **doc, "ignored_links": ["base_link"]}
    (tmp_path / "robot.yaml").write_text(yaml.safe_dump(doc, sort_keys=False))
    rc, out, _ = larc(capsys, "certify", REACH, "--scene", tmp_path / "table.yaml", "--robot", tmp_path / "robot.yaml")
    assert rc == 0 and "excludes links: base_link" in out
    doc["ignored_links"] = ["link4"]
    (tmp_path / "robot.yaml").write_text(yaml.safe_dump(doc, sort_keys=False))
    rc, _, err = larc(capsys, "certify", REACH, "--scene", tmp_path / "table.yaml", "--robot", tmp_path / "robot.yaml")
    assert rc == 2 and "robot.yaml: ignored_links: link4" in err and "moves" in err
    doc["ignored_links"] = "base_link"
    (tmp_path / "robot.yaml").write_text(yaml.safe_dump(doc, sort_keys=False))
    rc, _, err = larc(capsys, "certify", REACH, "--scene", tmp_path / "table.yaml", "--robot", tmp_path / "robot.yaml")
    assert rc == 2 and "ignored_links must be a list" in err


def test_explain_with_ignore_link(tmp_path, capsys):
    (tmp_path / "table.yaml").write_text(TABLE)
    rc, out, _ = larc(capsys, "explain", REACH, "--scene", tmp_path / "table.yaml", "--ignore-link", "base_link",
                      "-o", tmp_path / "e.png")
    assert rc == 0 and (tmp_path / "e.png").stat().st_size > 1000 and "CERTIFIED" in out
