"""``larc view``: a certificate in 3-D in the browser (viser).

:func:`view` serves, with viser (a web viewer driven from Python; its client ships with the
package, nothing is fetched from the internet), the scene of one or more trajectories
(:class:`~larc_jax.products.view_data.ViewData`, from a certificate file or from the files
``larc certify`` read and its ``--leaves`` table):

* the robot's collision meshes (orange), placed by the NumPy forward kinematics at the time of
  the time slider; a play checkbox animates it;
* the obstacle boxes (blue);
* the leaf cover as a timeline image coloured by what decided each leaf (green: capsule test,
  teal: hull test, purple: a self-collision pair recorded, red: not passed), and as points on the
  gripper path at each leaf's midpoint in the same colours;
* for the selected leaf (leaf slider; default the first inconclusive leaf, else the tightest):
  the capsules at its midpoint with their inflation shells (radius + margin + motion radius b,
  recomputed by the float64 reference), the recorded pair in red (capsule and box, or the two
  capsules of a self pair) and the segment joining its closest points; for a leaf the hull test
  passed, also the hull parts of the recorded link (teal; their few-mm padding and motion shells
  are not drawn).

:meth:`Viewer.run` blocks, stepping the animation, until Ctrl-C (then it stops the server and
returns). Nothing here imports JAX.
"""

from __future__ import annotations

import math
import signal
import threading
import time

import numpy as np

from ..errors import LarcInputError
from ..model.shapes import shape_mesh
from .view_data import (STAGE_COLOURS, ViewData, deciding, leaf_colours, leaf_detail, link_meshes, link_poses, timeline_image,
                        wxyz)

__all__ = ["Viewer", "view", "ROBOT_RGB", "BOX_RGB", "PAIR_RGB"]

ROBOT_RGB = (255, 140, 0)
BOX_RGB = (30, 90, 230)
PAIR_RGB = (220, 20, 60)
HULL_RGB = (0, 131, 143)
_CAPSULE_RGB = (150, 160, 175)


def _capsule_mesh(a: np.ndarray, b: np.ndarray, r: float):
    """Vertices and faces of the capsule of axis [a, b] and radius r (base frame)."""
    import trimesh

    d = b - a
    length = float(np.linalg.norm(d))
    mesh = trimesh.creation.capsule(height=max(length, 1e-9), radius=max(float(r), 1e-6), count=[12, 12])
    z = d / length if length > 1e-12 else np.array([0.0, 0.0, 1.0])
    helper = np.array([1.0, 0.0, 0.0]) if abs(z[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    x = np.cross(helper, z)
    x /= np.linalg.norm(x)
    rot = np.column_stack([x, np.cross(z, x), z])
    v = np.asarray(mesh.vertices) @ rot.T + 0.5 * (a + b)
    return v.astype(np.float32), np.asarray(mesh.faces, np.uint32)


def _default_leaf(lv) -> int:
    bad = np.flatnonzero(~lv.certified)
    if len(bad):
        return int(bad[0])
    g = np.where(np.isnan(lv.clearance_m), -np.inf, lv.clearance_m)
    return int(np.argmin(g))


class Viewer:
    """A running viser server showing :class:`ViewData` (module docstring)."""

    def __init__(self, data: ViewData, *, host: str = "127.0.0.1", port: int = 8080):
        try:
            import viser
        except ImportError:
            raise LarcInputError("larc view needs viser (pip install 'larc_jax[view]')") from None
        if not data.items:
            raise LarcInputError(f"{data.source}: no trajectory to show")
        self.data = data
        self.server = viser.ViserServer(host=host, port=port, verbose=False)
        self.url = f"http://{host}:{self.server.get_port()}"
        self.meshes = link_meshes(data.robot)
        self.robot_handles: dict[int, object] = {}
        self.box_handles: list = []
        self.leaf_handles: list = []
        self._item = 0
        # Look at the robot and the boxes from the front right, above.
        cam = self.server.initial_camera
        cam.position, cam.look_at = (0.95, -1.05, 0.8), (0.05, 0.0, 0.2)
        self.server.scene.add_grid("/ground", width=2.0, height=2.0, cell_size=0.1, section_size=0.5)
        self._build_gui()
        self.show_trajectory(0)

    # --- GUI -------------------------------------------------------------------------------
    def _build_gui(self) -> None:
        gui, data = self.server.gui, self.data
        ids = [it.traj.id for it in data.items]
        self.traj_menu = gui.add_dropdown("trajectory", options=ids, initial_value=ids[0])
        self.time_slider = gui.add_slider("time (s)", min=0.0, max=1.0, step=1e-3, initial_value=0.0)
        self.play = gui.add_checkbox("play", initial_value=False)
        self.leaf_slider = gui.add_slider("leaf", min=0, max=1, step=1, initial_value=0)
        self.show_leaf = gui.add_checkbox("show leaf enclosures", initial_value=True)
        self.timeline = gui.add_image(np.zeros((28, 480, 3), np.uint8), label="leaf cover", format="png")
        self.info = gui.add_markdown("")
        legend = ", ".join(f"{k}: rgb{v}" for k, v in STAGE_COLOURS.items())
        gui.add_markdown(f"Timeline colours — {legend}. Orange: robot; blue: boxes; red: the recorded pair.")
        self.traj_menu.on_update(lambda _: self.show_trajectory(ids.index(self.traj_menu.value)))
        self.time_slider.on_update(lambda _: self.set_time(self.time_slider.value))
        self.leaf_slider.on_update(lambda _: self.select_leaf(int(self.leaf_slider.value)))
        self.show_leaf.on_update(lambda _: self.select_leaf(int(self.leaf_slider.value)))

    @property
    def item(self):
        return self.data.items[self._item]

    # --- scene -----------------------------------------------------------------------------
    def show_trajectory(self, i: int) -> None:
        """Draw trajectory ``i``: its scene's boxes, the robot at its start, its leaf cover."""
        self._item = i
        it, scene = self.data.items[i], self.data.items[i].scene
        sc = self.server.scene
        for h in self.box_handles + self.leaf_handles:
            h.remove()
        self.box_handles = [
            sc.add_box(f"/boxes/{k}", color=BOX_RGB, dimensions=tuple(scene.hi[k] - scene.lo[k]),
                       position=tuple(0.5 * (scene.hi[k] + scene.lo[k])), opacity=0.85)
            for k in range(scene.n_boxes)]
        for k in range(scene.shapes.count):  # posed shapes, faceted for drawing
            mesh = shape_mesh(scene.shapes, k)
            self.box_handles.append(sc.add_mesh_simple(
                f"/shapes/{k}", np.asarray(mesh.vertices, np.float32), np.asarray(mesh.faces, np.uint32),
                color=BOX_RGB, opacity=0.85))
        if scene.point_sets.count:  # meshes and clouds: the vertices of their pieces
            points = np.concatenate(scene.point_sets.pieces).astype(np.float32)
            self.box_handles.append(sc.add_point_cloud("/points", points=points, colors=BOX_RGB, point_size=0.004))
        t0, t1 = float(it.traj.t[0]), float(it.traj.t[-1])
        self.time_slider.min, self.time_slider.max = t0, max(t1, t0 + 1e-3)
        self.time_slider.step = max((t1 - t0) / 1000, 1e-6)
        self.leaf_handles = []
        if it.leaves is not None and len(it.leaves):
            mids = 0.5 * (it.leaves.t0 + it.leaves.t1)
            tool = max(self.meshes) if self.meshes else self.data.robot.n_links - 1
            pts = np.array([link_poses(self.data.robot, it.traj, t)[tool, :3, 3] for t in mids], np.float32)
            self.leaf_handles.append(sc.add_point_cloud("/leaves", points=pts, colors=leaf_colours(it.leaves),
                                                        point_size=0.012, point_shape="circle"))
            self.leaf_slider.max = max(len(it.leaves) - 1, 1)
            self.leaf_slider.value = _default_leaf(it.leaves)
            self.select_leaf(_default_leaf(it.leaves))
        else:
            self.info.content = f"**{it.traj.id}**: no leaf cover given (a certificate or `--leaves` table shows it)"
            self.set_time(t0)

    def set_time(self, t: float) -> None:
        """Place the robot's links at time ``t``."""
        poses = link_poses(self.data.robot, self.item.traj, t)
        for li, (v, f) in self.meshes.items():
            T = poses[li]
            h = self.robot_handles.get(li)
            if h is None:
                h = self.server.scene.add_mesh_simple(f"/robot/{self.data.robot.link_names[li]}", v, f,
                                                      color=ROBOT_RGB)
                self.robot_handles[li] = h
            h.position, h.wxyz = tuple(T[:3, 3]), tuple(wxyz(T[:3, :3]))
        self._draw_timeline(t_now=t)

    def _draw_timeline(self, t_now=None) -> None:
        it = self.item
        if it.leaves is not None and len(it.leaves):
            self.timeline.image = timeline_image(it.leaves, float(it.traj.t[0]), float(it.traj.t[-1]),
                                                 selected=self._leaf, t_now=t_now)

    _leaf: int | None = None
    _leaf_nodes: tuple = ()

    def select_leaf(self, j: int) -> None:
        """Show leaf ``j``'s capsules at its midpoint, their shells and the recorded pair."""
        for h in self._leaf_nodes:
            h.remove()
        self._leaf_nodes = ()
        it, data = self.item, self.data
        if it.leaves is None or not 0 <= j < len(it.leaves):
            return
        self._leaf = j
        lv, caps = it.leaves, data.capsules
        det = leaf_detail(data, it, j)
        self.info.content = (
            f"**{it.traj.id}** leaf {j + 1}/{len(lv)}: t = [{lv.t0[j]:.4f}, {lv.t1[j]:.4f}] s, "
            f"{deciding(lv, j)}, clearance {lv.clearance_m[j] * 1000:+.2f} mm"
            + (f", capsule {caps.names[det.capsule]}" if det.capsule >= 0 else "")
            + (f" / capsule {caps.names[det.other]}" if det.other >= 0 else
               f" / obstacle {it.scene.obstacle_names[det.box]}" if 0 <= det.box < it.scene.n_obstacles else ""))
        if not self.show_leaf.value:
            return
        sc, nodes = self.server.scene, []
        for c in range(caps.n_capsules):
            mine = c in (det.capsule, det.other)
            rgb = PAIR_RGB if mine else _CAPSULE_RGB
            v, f = _capsule_mesh(det.seg_a[c], det.seg_b[c], det.radius[c])
            nodes.append(sc.add_mesh_simple(f"/leaf/capsule{c}", v, f, color=rgb, opacity=0.55))
            v, f = _capsule_mesh(det.seg_a[c], det.seg_b[c], det.shell_radius[c])
            nodes.append(sc.add_mesh_simple(f"/leaf/shell{c}", v, f, color=rgb, opacity=0.12 if mine else 0.06))
        for n, pts in enumerate(det.hull_parts):  # the hull test decided: its parts of the recorded link
            import trimesh

            hull = trimesh.convex.convex_hull(pts)
            nodes.append(sc.add_mesh_simple(f"/leaf/hull{n}", np.asarray(hull.vertices, np.float32),
                                            np.asarray(hull.faces, np.uint32), color=HULL_RGB, opacity=0.6))
        if 0 <= det.box < it.scene.n_boxes and det.other < 0:
            k = det.box
            nodes.append(sc.add_box("/leaf/box", color=PAIR_RGB, dimensions=tuple(it.scene.hi[k] - it.scene.lo[k]),
                                    position=tuple(0.5 * (it.scene.hi[k] + it.scene.lo[k])), wireframe=True))
        elif it.scene.n_boxes <= det.box < it.scene.n_boxes + it.scene.shapes.count and det.other < 0:
            mesh = shape_mesh(it.scene.shapes, det.box - it.scene.n_boxes)
            nodes.append(sc.add_mesh_simple("/leaf/box", np.asarray(mesh.vertices, np.float32),
                                            np.asarray(mesh.faces, np.uint32), color=PAIR_RGB, wireframe=True))
        elif det.box < it.scene.n_obstacles and det.other < 0 and det.box >= 0:  # a piece: its bounding box
            piece = it.scene.point_sets.pieces[det.box - it.scene.n_boxes - it.scene.shapes.count]
            lo, hi = piece.min(axis=0), piece.max(axis=0)
            nodes.append(sc.add_box("/leaf/box", color=PAIR_RGB, dimensions=tuple(np.maximum(hi - lo, 1e-4)),
                                    position=tuple(0.5 * (hi + lo)), wireframe=True))
        if det.closest is not None:
            seg = np.array([[det.closest[0], det.closest[1]]], np.float32)
            nodes.append(sc.add_line_segments("/leaf/closest", points=seg, colors=(0, 0, 0), thickness=0.003))
        self._leaf_nodes = tuple(nodes)
        self.time_slider.value = det.t_mid  # the robot where the capsules are (its on_update redraws)
        self.set_time(det.t_mid)

    # --- loop ------------------------------------------------------------------------------
    def step(self, dt: float) -> None:
        """Advance the animation by ``dt`` seconds if playing (wrapping at the end)."""
        if not self.play.value:
            return
        lo, hi = self.time_slider.min, self.time_slider.max
        t = self.time_slider.value + dt
        self.time_slider.value = lo if t > hi else t

    def run(self, fps: float = 30.0, *, announce: str | None = None) -> None:
        """Serve until Ctrl-C, animating when ``play`` is on; then stop the server. ``announce``
        is printed once the Ctrl-C handler is in place: a process started in the background begins
        with SIGINT ignored, so a Ctrl-C sent on reading a line printed earlier would be lost.

        In the main thread Ctrl-C only sets a flag that the loop reads: a KeyboardInterrupt raised
        inside viser's calls (a slider update waiting on the server's event loop) could leave
        the server unable to stop, and the process would hang on its threads. The handler takes
        no lock: Python runs it in the main thread between any two bytecodes, so one that called
        ``threading.Event.set`` while the loop sat inside ``Event.wait`` (which holds the event's
        lock while it queues its waiter) would block on that lock forever -- the hang this loop
        had before it slept with ``time.sleep``, which a signal interrupts without a lock held."""
        stop = [False]
        main = threading.current_thread() is threading.main_thread()
        previous = signal.signal(signal.SIGINT, lambda *_: stop.__setitem__(0, True)) if main else None
        try:
            if announce is not None:
                print(announce, flush=True)
            while not stop[0]:
                time.sleep(1.0 / fps)
                self.step(1.0 / fps)
        except KeyboardInterrupt:
            pass
        finally:
            if main:
                signal.signal(signal.SIGINT, previous)
            self.stop()

    def stop(self) -> None:
        self.server.stop()


def view(certificate=None, *, trajectories=None, scene=None, robot=None, leaves=None, data: ViewData | None = None,
         host: str = "127.0.0.1", port: int = 8080, block: bool = True) -> Viewer:
    """Open the 3-D view (module docstring) of a certificate file, or of ``trajectories`` (files)
    in ``scene`` (file) with ``robot`` (robot file; None: PIPER) and their ``leaves`` table, or
    of ``data``. Prints the URL; with ``block`` serves until Ctrl-C. Returns the :class:`Viewer`."""
    from .view_data import read_view_certificate, read_view_files

    if data is None:
        if certificate is not None:
            data = read_view_certificate(certificate)
        elif trajectories and scene is not None:
            data = read_view_files(trajectories, scene, robot, leaves)
        else:
            raise LarcInputError("view: give a certificate file, or trajectory files and a scene file")
    viewer = Viewer(data, host=host, port=port)
    shown = "localhost" if host in ("0.0.0.0", "::") else host
    url = f"larc view: open http://{shown}:{viewer.server.get_port()} in a browser (Ctrl-C to stop)"
    try:
        if block:
            viewer.run(announce=url)
        else:
            print(url, flush=True)
    except KeyboardInterrupt:
        # Ctrl-C right after the URL, before run() took over: still stop the server, whose
        # threads would otherwise keep the process alive.
        viewer.stop()
        if not block:
            raise
    return viewer


def view_command(args) -> int:
    """``larc view`` (:mod:`larc_jax.drivers.cli`): one certificate file, or trajectory files with ``--scene``."""
    if args.scene is None:
        if len(args.inputs) != 1 or args.leaves or args.robot:
            raise LarcInputError("larc view: give one certificate file, or trajectory files with --scene")
        view(args.inputs[0], host=args.host, port=args.port)
    else:
        view(trajectories=args.inputs, scene=args.scene, robot=args.robot, leaves=args.leaves, host=args.host,
             port=args.port)
    return 0
