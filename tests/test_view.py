"""larc view (viser): the scene it builds (meshes, boxes, leaf markers, a leaf's enclosures), the
readers (certificate file, --leaves table), Ctrl-C, and a real headless Chromium loading the page.

The browser test needs a `chromium` on PATH (.ci/run installs it) and skips without one. Its
screenshot is kept only where ``LARC_VIEW_SCREENSHOT_OUT`` names a file (the README's picture)."""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from larc_jax.drivers.cli import EXIT_OK, main
from larc_jax.obstacles.geometry import segment_box_distance_np
from larc_jax.products.view_data import (STAGE_COLOURS, leaf_detail, link_meshes, read_view_certificate, read_view_files,
                                timeline_image)
from tests.browser import chromium_page, free_port, screenshots

ROOT = Path(__file__).resolve().parent.parent
EX = ROOT / "configs" / "examples"
REACH, SWEEP, CELL = (str(EX / n) for n in ("reach_left.yaml", "sweep_front.yaml", "cell.yaml"))
pytest.importorskip("viser", reason="larc view needs viser (pip install 'larc_jax[view]')")


@pytest.fixture(scope="module")
def cert(tmp_path_factory):
    """A certificate and leaf table of reach_left (certified) and sweep_front (not), NumPy reference,
    hull cascade and self-collision test: leaves decided by the capsule, hull and self tests (with
    1 mm of padding: with the cascade's default, none, the capsule test alone passes reach_left)."""
    d = tmp_path_factory.mktemp("view")
    path, leaves = d / "cert.json", d / "leaves.csv"
    assert main(["certify", REACH, SWEEP, "--scene", CELL, "--method", "reference", "--max-depth", "5",
                 "--padding", "0.001", "--self-collision", "--certificate", str(path), "--leaves", str(leaves),
                 "--no-fail-on-uncertified", "-q"]) == EXIT_OK
    return path, leaves


@pytest.fixture(scope="module")
def viewer(cert):
    from larc_jax.products.view import view

    v = view(cert[0], port=free_port(), block=False)
    yield v
    v.stop()


def test_readers_agree(cert):
    a = read_view_certificate(cert[0])
    b = read_view_files([REACH, SWEEP], CELL, leaves=cert[1], padding_m=0.001)
    np.testing.assert_array_equal(np.asarray(a.capsules.radius), np.asarray(b.capsules.radius))  # the run's padding
    assert a.capsules.padding_m == 0.001 and read_view_files([REACH], CELL).capsules.padding_m == 0.0
    assert [it.traj.id for it in a.items] == [it.traj.id for it in b.items] == ["reach_left", "sweep_front"]
    for x, y in zip(a.items, b.items):
        for col in ("depth", "index", "t0", "t1", "certified", "capsule", "box", "other_capsule", "stage"):
            np.testing.assert_array_equal(getattr(x.leaves, col), getattr(y.leaves, col), err_msg=col)
        np.testing.assert_allclose(x.leaves.clearance_m, y.leaves.clearance_m, rtol=1e-12)
    assert a.items[0].leaves.certified.all() and not a.items[1].leaves.certified.all()


def test_scene_has_the_robot_boxes_and_leaves(viewer):
    data = viewer.data
    assert len(viewer.robot_handles) == len(link_meshes(data.robot)) > 0
    assert len(viewer.box_handles) == data.items[0].scene.n_boxes == 3
    (cloud,) = viewer.leaf_handles
    assert len(cloud.points) == len(data.items[0].leaves)
    C = data.capsules.n_capsules
    lv0 = data.items[0].leaves
    viewer.select_leaf(int(np.flatnonzero((lv0.stage == 1) & (lv0.box >= 0))[0]))  # capsule test, box pair
    assert len(viewer._leaf_nodes) == 2 * C + 2  # capsules, shells, the recorded box, closest points
    j = int(np.flatnonzero(lv0.stage == 2)[0])  # the hull test decided: its parts of the recorded link are drawn
    n_parts = len(leaf_detail(data, data.items[0], j).hull_parts)
    viewer.select_leaf(j)
    assert n_parts >= 1 and len(viewer._leaf_nodes) == 2 * C + n_parts + 2
    viewer.show_trajectory(1)  # not certified: the first inconclusive leaf is shown
    lv = data.items[1].leaves
    assert viewer._leaf == int(np.flatnonzero(~lv.certified)[0])
    assert "inconclusive" in viewer.info.content
    t = viewer.time_slider.value
    assert lv.t0[viewer._leaf] <= t <= lv.t1[viewer._leaf]  # the robot is shown at the leaf's midpoint
    viewer.show_trajectory(0)


def test_leaf_detail_closest_points_are_the_recorded_pair(viewer):
    data = viewer.data
    it = data.items[1]
    j = int(np.flatnonzero(~it.leaves.certified)[0])
    det = leaf_detail(data, it, j)
    c, k = det.capsule, det.box
    a, b = det.closest
    d = segment_box_distance_np(det.seg_a[c], det.seg_b[c], it.scene.lo[k], it.scene.hi[k])
    assert abs(np.linalg.norm(a - b) - d) < 1e-6
    assert np.all(det.shell_radius > det.radius)
    # the recorded clearance is the distance minus the shell (up to the guard)
    assert abs((d - det.shell_radius[c]) - it.leaves.clearance_m[j]) < 1e-6


def test_self_pair_and_hull_parts(viewer):
    from larc_jax.leaf.self_collision import segment_segment_distance_np

    data = viewer.data
    it = data.items[0]
    j = int(np.flatnonzero(it.leaves.other_capsule >= 0)[0])  # a recorded self-collision pair
    det = leaf_detail(data, it, j)
    c, o = det.capsule, det.other
    d = segment_segment_distance_np(det.seg_a[c], det.seg_b[c], det.seg_a[o], det.seg_b[o])
    assert abs(np.linalg.norm(det.closest[0] - det.closest[1]) - d) < 1e-6
    j = int(np.flatnonzero(it.leaves.stage == 2)[0])
    det = leaf_detail(data, it, j)
    c = det.capsule
    link = data.capsules.link_index[c]
    parts = [p for p in range(len(data.hulls.names)) if data.hulls.link_index[p] == link]
    assert len(det.hull_parts) == len(parts) >= 1
    # the parts sit on the link: the capsule (which encloses the link) reaches every hull vertex
    for pts in det.hull_parts:
        a, b = det.seg_a[c], det.seg_b[c]
        u = np.clip((pts - a) @ (b - a) / max((b - a) @ (b - a), 1e-300), 0, 1)
        assert np.all(np.linalg.norm(pts - (a + u[:, None] * (b - a)), axis=1) < det.radius[c] + 0.01)


def test_view_never_imports_jax(cert):
    code = ("import sys; from larc_jax.products.view_data import read_view_certificate, leaf_detail; "
            f"d = read_view_certificate({str(cert[0])!r}); leaf_detail(d, d.items[1], 0); "
            "import larc_jax.products.view; assert 'jax' not in sys.modules, 'jax imported'")
    subprocess.run([sys.executable, "-c", code], check=True, timeout=120)


def test_timeline_colours(viewer):
    lv = viewer.data.items[1].leaves
    img = timeline_image(lv, float(lv.t0[0]), float(lv.t1[-1]), width=400)
    colours = {tuple(p) for p in img[10]}
    assert STAGE_COLOURS["capsule"] in colours and STAGE_COLOURS["inconclusive"] in colours
    j = int(np.flatnonzero(~lv.certified)[0])
    x = int((0.5 * (lv.t0[j] + lv.t1[j]) - lv.t0[0]) / (lv.t1[-1] - lv.t0[0]) * 400)
    assert tuple(img[10, x]) == STAGE_COLOURS["inconclusive"]


def communicate_or_dump(p, timeout):
    """``p.communicate``; if ``p`` (started with ``-X faulthandler``) hangs, SIGABRT makes it print
    every thread's stack to its stderr, which the failure then shows."""
    try:
        return p.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        p.send_signal(signal.SIGABRT)
        out, err = p.communicate(timeout=30)
        pytest.fail(f"no exit within {timeout} s after Ctrl-C; its threads:\n{err[-8000:]}")


def test_cli_prints_the_url_and_stops_on_ctrl_c(cert):
    port = free_port()
    # Started with SIGINT ignored, as a background job (CI) starts: a URL printed before the
    # handler was in place let this test's Ctrl-C be dropped and the viewer serve forever.
    p = subprocess.Popen([sys.executable, "-X", "faulthandler", "-m", "larc_jax.drivers.cli", "view", str(cert[0]),
                          "--port", str(port)], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                         preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_IGN))
    try:
        line = ""
        deadline = time.time() + 60
        while "larc view: open" not in line and time.time() < deadline:
            line = p.stdout.readline()
            assert line or p.poll() is None, p.stderr.read()
        assert f"http://127.0.0.1:{port}" in line
        p.send_signal(signal.SIGINT)
        out, err = communicate_or_dump(p, 30)
    finally:
        if p.poll() is None:
            p.kill()
    assert p.returncode == 0, err
    assert "Traceback" not in err


# Ctrl-C landing while the serving loop waits between frames. Python runs a signal handler in the
# main thread between two bytecodes, wherever the loop is; a handler that took a lock the wait
# held (threading.Event.set inside Event.wait, the loop before) blocked forever. Here the handler
# runs from inside the loop's wait itself, every frame from the third on, exactly as a signal can.
CTRL_C_IN_THE_WAIT = """
import signal, sys, time, types
from larc_jax.products import view as V
before = signal.getsignal(signal.SIGINT)  # SIG_IGN where the test runs in the background (CI)
v = V.view(sys.argv[1], port=int(sys.argv[2]), block=False)
v.play.value = True
calls = [0]
def sleep(seconds):
    calls[0] += 1
    if calls[0] >= 3:
        signal.getsignal(signal.SIGINT)(signal.SIGINT, None)
    time.sleep(seconds)
V.time = types.SimpleNamespace(sleep=sleep)
v.run(fps=200.0)
assert signal.getsignal(signal.SIGINT) is before, "Ctrl-C handler not restored"
print("stopped after", calls[0], "waits", flush=True)
"""


def test_ctrl_c_during_the_wait_stops_the_loop(cert):
    p = subprocess.Popen([sys.executable, "-X", "faulthandler", "-c", CTRL_C_IN_THE_WAIT, str(cert[0]),
                          str(free_port())], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        out, err = communicate_or_dump(p, 60)
    finally:
        if p.poll() is None:
            p.kill()
    assert p.returncode == 0, err
    assert "stopped after 3 waits" in out, out + err


def test_cli_bad_input_exits_2(tmp_path, capsys):
    bad = tmp_path / "x.json"
    bad.write_text("{}")
    assert main(["view", str(bad)]) == 2
    assert "not a larc certificate" in capsys.readouterr().err


CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser") or shutil.which("google-chrome")


@pytest.mark.slow
@pytest.mark.skipif(CHROMIUM is None, reason="no chromium on PATH (apt-get install chromium; .ci/run does)")
def test_browser_shows_the_robot_and_the_boxes(viewer, tmp_path):
    """Headless Chromium (software WebGL) loads the page; the screenshot shows the orange robot
    and the blue boxes in the 3-D canvas. External hosts resolve to nothing: the client must be
    served whole by viser."""
    from PIL import Image

    from larc_jax.products.view import BOX_RGB, ROBOT_RGB

    viewer.show_trajectory(0)
    w, h = 1280, 800
    assert ROBOT_RGB[0] - ROBOT_RGB[2] > 110 and BOX_RGB[2] - BOX_RGB[0] > 70  # the classes match the colours
    # The meshes reach the page over a websocket in real time, so the page runs in real time and is
    # photographed until the robot and the boxes show or 150 s pass (tests/browser.py says why not
    # Chromium's --virtual-time-budget). Both colour counts are needed: the client's fade-in
    # animations wash the colours out for a moment after the meshes arrive.
    shot = tmp_path / "view.png"
    with chromium_page(CHROMIUM, viewer.url, w, h) as shoot:
        for png in screenshots(shoot, timeout_s=150):
            shot.write_bytes(png)
            img = np.asarray(Image.open(shot).convert("RGB")).astype(int)
            assert img.shape[:2] == (h, w)
            r, g, b = img[..., 0], img[..., 1], img[..., 2]
            orange = (r > 170) & (g > 70) & (g < 200) & (b < 110) & (r - b > 110)
            blue = (b > 140) & (b - r > 70) & (b - g > 30)
            canvas = np.zeros_like(orange)
            canvas[150:, : w - 340] = True  # the 3-D view, left of the control panel, below the notice
            if (orange & canvas).sum() > 400 and (blue & canvas).sum() > 400:
                break
    assert img.std() > 10, "blank page"
    assert (orange & canvas).sum() > 400, "no robot in the picture"
    assert (blue & canvas).sum() > 400, "no obstacle in the picture"
    ys, xs = np.nonzero(orange & canvas)
    assert w * 0.2 < xs.mean() < w * 0.75 and h * 0.2 < ys.mean() < h * 0.8, "the robot is not in the middle"
    out = os.environ.get("LARC_VIEW_SCREENSHOT_OUT")
    if out:
        Path(out).parent.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(shot, out)
