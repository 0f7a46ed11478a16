"""Hostile files get one line and exit 2, quickly (issue 18): non-regular files (a FIFO, a link
to /dev/zero, a directory), files larger than the cap or growing while read, overflowing hex
floats, huge integers, deep nesting, duplicate keys (JSON and YAML), control characters in
quoted text; and the checker refuses more leaves than the certificate's depth allows, before any
per-leaf work. Non-regular files are read in a child process with a timeout, so a reader that
blocks fails the test instead of hanging it."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path

import pytest

import larc_jax.io as lio
from larc_jax.drivers.cli import EXIT_BAD_INPUT, EXIT_OK, main
from larc_jax.enclosure.robot_file import load_robot_file
from larc_jax.errors import LarcInputError, one_line
from larc_jax.model.scene import read_scene
from larc_jax.model.trajectory_files import read_trajectory
from larc_jax.products.verify import Refuted, verify_certificate

ROOT = Path(__file__).resolve().parent.parent
EX = ROOT / "configs" / "examples"
REACH, CELL = EX / "reach_left.yaml", EX / "cell.yaml"
DEPTH = 4
FAST_S = 5.0
"""A refusal must come within this (seconds; generous for a loaded 2-core machine)."""


@pytest.fixture(scope="module")
def cert(tmp_path_factory):
    """A real certificate (reach_left certified in cell.yaml at depth 4) and its document."""
    path = tmp_path_factory.mktemp("cert") / "cert.json"
    assert main(["certify", str(REACH), "--scene", str(CELL), "--max-depth", str(DEPTH), "--certificate", str(path),
                 "-q"]) == EXIT_OK
    doc = json.loads(path.read_text())
    assert doc["trajectories"][0]["certified"]
    return path, doc


# ---------------------------------------------------------------------------------------------- non-regular files

_CHILD = r"""
import json, sys, time
import larc_jax.products.verify as v  # defers JAX first, as `larc verify` does
from larc_jax.enclosure.robot_file import load_robot_file
from larc_jax.errors import LarcInputError
from larc_jax.drivers.manifest import iter_manifest
from larc_jax.model.scene import read_scene
from larc_jax.model.trajectory_files import read_trajectory
from larc_jax.model.urdf import file_sha256

folder, cert = sys.argv[1], sys.argv[2]
readers = {
    "scene_yaml": lambda p: read_scene(p + ".yaml"), "scene_moveit": lambda p: read_scene(p + ".scene"),
    "trajectory_yaml": lambda p: read_trajectory(p + ".yaml"), "trajectory_json": lambda p: read_trajectory(p + ".json"),
    "trajectory_csv": lambda p: read_trajectory(p + ".csv"), "robot_file": lambda p: load_robot_file(p + ".yaml"),
    "manifest": lambda p: list(iter_manifest(p + ".csv")), "certificate": lambda p: v.verify_certificate(p + ".json"),
    "verify_trajectory": lambda p: v.verify_certificate(cert, trajectories=[p + ".yaml"]),
    "verify_scene": lambda p: v.verify_certificate(cert, scenes=[p + ".yaml"]),
    "file_sha256": lambda p: file_sha256(p + ".yaml"),
}
out = {}
for kind in ("fifo", "zero", "dir"):
    for name, read in readers.items():
        t = time.monotonic()
        try:
            read(f"{folder}/{kind}")
            result = "accepted"
        except LarcInputError as exc:
            result = "LarcInputError: " + str(exc)
        except Exception as exc:
            result = f"{type(exc).__name__}: {exc}"
        out[f"{name}/{kind}"] = [result, time.monotonic() - t]
print(json.dumps(out))
"""
READERS = ("scene_yaml", "scene_moveit", "trajectory_yaml", "trajectory_json", "trajectory_csv", "robot_file",
           "manifest", "certificate", "verify_trajectory", "verify_scene", "file_sha256")
KINDS = {"fifo": "FIFO", "zero": "device", "dir": "directory"}


@pytest.fixture(scope="module")
def non_regular(tmp_path_factory, cert):
    folder = tmp_path_factory.mktemp("hostile")
    for suffix in (".yaml", ".scene", ".json", ".csv"):
        os.mkfifo(folder / f"fifo{suffix}")
        (folder / f"zero{suffix}").symlink_to("/dev/zero")
        (folder / f"dir{suffix}").mkdir()
    proc = subprocess.run([sys.executable, "-c", _CHILD, str(folder), str(cert[0])], capture_output=True, text=True,
                          timeout=120)
    assert proc.returncode == 0, proc.stderr
    return json.loads(proc.stdout.strip().splitlines()[-1])


@pytest.mark.parametrize("kind", sorted(KINDS))
@pytest.mark.parametrize("reader", READERS)
def test_non_regular_files_are_refused_quickly(non_regular, reader, kind):
    result, seconds = non_regular[f"{reader}/{kind}"]
    assert result.startswith("LarcInputError: ") and KINDS[kind] in result and f"{kind}." in result, result
    # verify_* load the certificate's robot (URDF, mesh hashes) before they reach the file
    assert len(result.splitlines()) == 1 and seconds < (30.0 if reader.startswith("verify_") else FAST_S)


@pytest.mark.parametrize("args", [["verify", "{fifo}.json"], ["verify", "{zero}.json"],
                                  ["certify", str(REACH), "--scene", "{fifo}.yaml"]])
def test_cli_refuses_non_regular_files(tmp_path, args):
    os.mkfifo(tmp_path / "fifo.json")
    os.mkfifo(tmp_path / "fifo.yaml")
    (tmp_path / "zero.json").symlink_to("/dev/zero")
    argv = [a.format(fifo=tmp_path / "fifo", zero=tmp_path / "zero") for a in args]
    proc = subprocess.run([sys.executable, "-m", "larc_jax.drivers.cli", *argv], capture_output=True, text=True, timeout=120)
    assert proc.returncode == EXIT_BAD_INPUT and len(proc.stderr.strip().splitlines()) == 1, proc.stderr
    assert "expected a regular file" in proc.stderr


# ---------------------------------------------------------------------------------------------- the size cap

def test_reader_reads_at_most_the_cap_whatever_st_size_says(tmp_path, monkeypatch):
    """A file larger than the cap (one that grew after fstat, or whose st_size lies) is refused
    after reading cap + 1 bytes."""
    path = tmp_path / "scene.yaml"
    path.write_text("frame: base_link\nboxes: []\n" + "#" * 5000 + "\n")
    monkeypatch.setattr(lio, "MAX_INPUT_BYTES", 1000)
    reads = []
    real_read = os.read
    monkeypatch.setattr(lio.os, "read", lambda fd, n: reads.append(n) or real_read(fd, n))
    with pytest.raises(LarcInputError, match="larger than the 0 MiB limit"):
        read_scene(path)
    assert sum(reads) <= 1001
    monkeypatch.setattr(lio, "MAX_INPUT_BYTES", 10000)
    assert read_scene(path).n_boxes == 0


# ---------------------------------------------------------------------------------------------- hostile content

def _deep(n=100_000):
    return "[" * n


HOSTILE_TEXT = {
    "trajectory.yaml": {"deep": _deep(), "deep_65": "a: " + "[" * 65 + "]" * 65,
                        "duplicate": REACH.read_text() + "joint_names: [joint1]\n",
                        "huge_int": REACH.read_text().replace("0.7,", "1" + "0" * 400 + ",", 1),
                        "alias_bomb": "a: &a [1,2,3,4,5,6,7,8,9]\n" + "".join(
                            f"{c}: &{c} [{', '.join([f'*{p}'] * 9)}]\n" for p, c in zip("abcde", "bcdef"))},
    "trajectory.json": {"deep": _deep(), "duplicate": '{"points": [], "points": []}',
                        "huge_int": '{"joint_names": ["joint1"], "points": [{"positions": [1' + "0" * 5000 + "]}]}"},
    "scene.yaml": {"deep": "boxes: " + _deep(), "duplicate": CELL.read_text() + "boxes: []\n",
                   "huge_int": "frame: base_link\nboxes:\n  - {min: [0, 0, 0], max: [1" + "0" * 400 + ", 1, 1]}\n",
                   "self_alias": "frame: base_link\nboxes: &b [*b]\n"},
    "robot.yaml": {"deep": "urdf: " + _deep(), "duplicate": "urdf: a.urdf\nurdf: b.urdf\n",
                   "huge_int": "urdf: a.urdf\nheld_joints: {joint7: 1" + "0" * 400 + "}\n"},
    "cert.json": {"deep": _deep(), "duplicate": '{"format": "larc-certificate", "format": "x"}'},
}
READ = {"trajectory.yaml": read_trajectory, "trajectory.json": read_trajectory, "scene.yaml": read_scene,
        "robot.yaml": load_robot_file,
        "cert.json": verify_certificate}


@pytest.mark.parametrize("name,case", [(n, c) for n, cases in HOSTILE_TEXT.items() for c in cases])
def test_hostile_content_is_one_line_quickly(tmp_path, name, case):
    path = tmp_path / name
    path.write_text(HOSTILE_TEXT[name][case])
    start = time.monotonic()
    with pytest.raises(LarcInputError) as err:
        READ[name](path)
    msg = str(err.value)
    assert msg.startswith(str(path)) and len(msg.splitlines()) == 1 and len(msg) < 400, msg
    assert time.monotonic() - start < FAST_S


def _edit(tmp_path, doc, edit, name="edited.json") -> Path:
    doc = json.loads(json.dumps(doc))
    edit(doc)
    path = tmp_path / name
    path.write_text(json.dumps(doc))
    return path


def _leaves(doc):
    return doc["trajectories"][0]["leaves"]


CERT_EDITS = {
    "margin a float.hex text": (lambda d: d["parameters"].update(margin_m="0x1p+1024"), "parameters: margin_m"),
    "margin 1e400": (lambda d: d["parameters"].update(margin_m=1e400), "parameters: margin_m"),
    "leaf t0 0x1p+1024": (lambda d: _leaves(d)["t0"].__setitem__(0, "0x1p+1024"), "leaves.t0[0]"),
    "rounding tau 0x1p+1024": (lambda d: d["trajectories"][0]["rounding"].update(tau_s="0x1p+1024"), "tau_s"),
    "leaf index 2**63": (lambda d: _leaves(d)["index"].__setitem__(0, 2**63), "leaves.index[0]"),
    "leaf depth 2**63": (lambda d: _leaves(d)["depth"].__setitem__(0, 2**63), "leaves.depth[0]"),
    "leaf capsule -2**64": (lambda d: _leaves(d)["capsule"].__setitem__(0, -2**64), "leaves.capsule[0]"),
    "max_depth 2**63": (lambda d: d["parameters"].update(max_depth=2**63), "parameters: max_depth"),
    "max_depth above the limit": (lambda d: d["parameters"].update(max_depth=21), "parameters: max_depth"),
    "scene index 2**63": (lambda d: d["trajectories"][0].update(scene=2**63), "scene"),
    "version 2**63": (lambda d: d.update(version=2**63), "version"),
}


@pytest.mark.parametrize("case", sorted(CERT_EDITS))
def test_certificate_numbers_out_of_range_exit_2(cert, tmp_path, capsys, case):
    edit, where = CERT_EDITS[case]
    path = _edit(tmp_path, cert[1], edit)
    with pytest.raises(LarcInputError, match=where.replace("[", r"\[").replace("]", r"\]")):
        verify_certificate(path)
    assert main(["verify", str(path)]) == EXIT_BAD_INPUT
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1 and "Traceback" not in err


def test_more_leaves_than_the_depth_allows_are_refused_before_leaf_work(cert, tmp_path):
    """2**max_depth dyadic pieces at most tile a horizon; one more leaf (here with a value the
    per-leaf parsing would refuse differently) is refuted from the count alone."""
    def add_leaves(d):
        lv = _leaves(d)
        extra = 2**DEPTH + 1 - len(lv["depth"])
        for key, column in lv.items():
            column.extend([column[-1]] * extra)
        lv["t0"][-1] = "not a float"
    path = _edit(tmp_path, cert[1], add_leaves)
    with pytest.raises(Refuted, match=rf"{2**DEPTH + 1} leaves, more than the 2\*\*{DEPTH}"):
        verify_certificate(path)


# ---------------------------------------------------------------------------------------------- one line

def test_messages_escape_control_characters():
    assert one_line("a\nb\r\tc\x1b[31m\u2028d") == "a\\nb\\r\\tc\\x1b[31m\\u2028d"
    err = LarcInputError("file\nname: bad\tfield")
    assert str(err) == "file\\nname: bad\\tfield"
    refuted = Refuted("trajectory 'a\nb'")
    assert "\n" not in str(refuted)


def test_scene_frame_with_a_newline_is_a_one_line_error(tmp_path, capsys):
    path = tmp_path / "nl.yaml"
    path.write_text('frame: "base\\nlink\\x1b[2J"\nboxes: []\n')
    with pytest.raises(LarcInputError) as err:
        read_scene(path, frame="base_link")
    assert "'base\\nlink\\x1b[2J'" in str(err.value) and "\n" not in str(err.value)
    assert main(["certify", str(REACH), "--scene", str(path), "-q"]) == EXIT_BAD_INPUT
    err_text = capsys.readouterr().err
    assert len(err_text.strip().splitlines()) == 1 and "\x1b" not in err_text
