"""The arguments of the ``larc`` command line: every subcommand's options, their defaults and help.

:func:`build_parser` builds the parser; each subcommand's name is ``args.command`` (the
handlers live in :mod:`larc_jax.drivers.cli`). A usage error raises :class:`UsageError` (one line, exit
2) instead of printing the usage block. No NumPy or JAX here: ``larc verify`` parses its
arguments without loading JAX.
"""

from __future__ import annotations

import argparse

from ..defaults import (DEFAULT_CHUNK_SIZE, DEFAULT_ENCLOSURE, DEFAULT_MARGIN_M, DEFAULT_MAX_DEPTH, DEFAULT_PADDING_M,
                       DEFAULT_RUN_PADDING_M, ENCLOSURES, METHODS, VELOCITY_MODES)
from ..errors import OneLineError
from ..run_spec import DTYPES
from ..products.verify_report import VerifyPins

__all__ = ["UsageError", "ArgumentParser", "build_parser", "spec_options"]


def output_options(in_subcommand: bool) -> argparse.ArgumentParser:
    """--quiet / --verbose / --progress / --compile-cache, accepted before and after the subcommand. In the
    subcommands their default is SUPPRESS, so a flag given before the subcommand survives."""
    o = argparse.ArgumentParser(add_help=False)
    g = o.add_argument_group("output")
    unset = {"default": argparse.SUPPRESS} if in_subcommand else {}
    g.add_argument("--quiet", "-q", action="store_true", **(unset or {"default": False}),
                   help="print nothing but errors (files asked for are still written)")
    g.add_argument("--verbose", "-v", action="store_true", **(unset or {"default": False}),
                   help="debug log messages on stderr")
    g.add_argument("--progress", action=argparse.BooleanOptionalAction, **(unset or {"default": None}),
                   help="progress bars on stderr (default: only when stderr is a terminal)")
    g.add_argument("--compile-cache", action=argparse.BooleanOptionalAction, **(unset or {"default": True}),
                   help="keep compiled kernels in ~/.cache/larc_jax (or $LARC_COMPILE_CACHE) so later runs "
                        "skip compiling (default: on; LARC_COMPILE_CACHE=0 also turns it off)")
    return o


class UsageError(OneLineError):
    """A command-line usage error (argparse's), reported like bad input: one line, exit 2."""


class ArgumentParser(argparse.ArgumentParser):
    """argparse, but a usage error raises :class:`UsageError` instead of printing the usage
    block and exiting, so ``main`` reports it as one ``larc: error:`` line (exit 2) and returns
    (``--help`` still prints and exits 0). Subparsers inherit the class."""

    def error(self, message):
        raise UsageError(f"{message} (see `{self.prog} --help`)")


def gripper_options(p: argparse.ArgumentParser, explain: bool = False) -> None:
    p.add_argument("--hold", action="append", metavar="JOINT=VALUE",
                   help="state the value of a held joint, e.g. the gripper fingers: --hold joint7=0 --hold "
                        "joint8=0 (repeatable). Without it a held finger may be anywhere in its stroke, which "
                        "the enclosures then cover (the output says which)")
    p.add_argument("--joints", metavar="J1,J2,...",
                   help="the joints the trajectories carry, if not the robot file's: e.g. add the fingers "
                        "(joint1,...,joint6,joint7,joint8) to certify a trajectory that moves the gripper")
    if explain:  # the picture shows capsules; the leaf's decision is the whole test's
        p.add_argument("--enclosure", default="capsules", choices=ENCLOSURES,
                       help="capsules (default) or hull, as for certify: the leaf is decided by that test; the "
                            "picture draws the capsule test's placed, inflated capsules")
    else:
        p.add_argument("--enclosure", default=DEFAULT_ENCLOSURE, choices=ENCLOSURES,
                       help="hull (default): capsule test, then the convex-hull test on the intervals it leaves "
                            "open; capsules: the capsule test alone (the paper's model)")


def spec_options(p: argparse.ArgumentParser, explain: bool = False) -> None:
    """The options of the run spec (:class:`~larc_jax.run_spec.RunSpec`) that certify and explain
    share, so every option works in both (``--method`` is certify's own)."""
    p.add_argument("--velocities", default="recorded", choices=VELOCITY_MODES,
                   help="recorded: use the file's velocities (default; a file without them is "
                        "refused); finite-difference: compute them from the positions (the "
                        "certificate then covers the Hermite curve through those velocities)")
    p.add_argument("--margin", type=float, default=DEFAULT_MARGIN_M,
                   help=f"clearance margin rho, m (default {DEFAULT_MARGIN_M})")
    p.add_argument("--padding", type=float, default=None, metavar="M",
                   help="padding added to every enclosure on top of its proven containment of the link meshes, m: "
                        "the certificate then states that every mesh clears the margin plus this (default: "
                        + ", ".join(f"{DEFAULT_RUN_PADDING_M[e]:g} for --enclosure {e}" for e in ENCLOSURES) + ")")
    p.add_argument("--swept", action="store_true",
                   help="add the swept test where the midpoint tests leave an interval open: each enclosure's hull "
                        "at the interval's two ends, grown by a radius that shrinks with the square of the interval "
                        "(certifies closer passes at a given depth)")
    p.add_argument("--max-depth", type=int, default=DEFAULT_MAX_DEPTH,
                   help=f"maximum bisection depth (default {DEFAULT_MAX_DEPTH})")
    p.add_argument("--dtype", default=DTYPES[0], choices=DTYPES,
                   help="geometry dtype: float64 (default) or float32 (the guard accounts for it; "
                        "--method reference is always float64)")
    p.add_argument("--self-collision", action="store_true",
                   help="also certify that no two links come into contact (capsule pairs not joined by a joint; "
                        "see larc_jax.leaf.self_collision); the output names the pairs not checked")
    p.add_argument("--self-margin", type=float, default=None, metavar="M",
                   help="with --self-collision: required distance between links, m (default 0: touching fails)")
    p.add_argument("--self-skip", action="append", metavar="LINK:LINK",
                   help="with --self-collision: do not check this link pair (repeatable; named in the output)")
    p.add_argument("--tracking-tolerance", metavar="RAD|JOINT=V,...",
                   help="certify every executed trajectory within this joint tracking error of the planned one: "
                        "one value for all active joints (rad; m for prismatic joints) or JOINT=VALUE,... (others 0)")
    p.add_argument("--ignore-link", action="append", metavar="LINK",
                   help="leave this link out of the certificate (repeatable): only a link that never "
                        "moves, e.g. a fixed base standing on its table; the output names it")
    gripper_options(p, explain)


def build_parser(description: str = "") -> argparse.ArgumentParser:
    """The parser of every subcommand; ``args.command`` names the one given."""
    p = ArgumentParser(
        prog="larc", description=description, parents=[output_options(False)],
        epilog="Exit status: 0 success / all certified, 1 some trajectory not certified, "
               "2 bad input or usage, 3 internal error.")
    sub = p.add_subparsers(dest="command", required=True)
    common = [output_options(True)]

    f = sub.add_parser("fit-capsules", help="fit proven capsules to a URDF's collision meshes",
                       parents=common)
    f.add_argument("urdf", help="URDF file")
    f.add_argument("-o", "--output", required=True, help="capsule YAML to write")
    f.add_argument("--package-dir", action="append", metavar="NAME=PATH",
                   help="folder of a ROS package named in package:// mesh URIs (repeatable)")
    f.add_argument("--capsules-per-link", action="append", metavar="LINK=N",
                   help="force 1 or 2 capsules on a link (repeatable)")
    f.add_argument("--n-capsules", type=int, default=None,
                   help="total capsule count: links that gain most from a split get two")
    f.add_argument("--padding", type=float, default=DEFAULT_PADDING_M, help="padding added to radii, m")
    f.add_argument("--joints", help="comma-separated active joints (default: the trunk chain)")
    f.add_argument("--hold", action="append", metavar="JOINT=VALUE",
                   help="value at which a non-active joint is held (repeatable); a held prismatic joint's "
                        "links are also fitted over its whole stroke (and alone, for a stated opening)")
    f.add_argument("--no-urdf-field", action="store_true",
                   help="do not record the URDF path in the file (e.g. for PIPER, found via env)")

    v = sub.add_parser(
        "verify-capsules", parents=common, help="re-prove that a capsule file contains its robot's collision geometry",
        description="Load a robot (capsule) file, check that its URDF and every collision mesh are the ones it was "
                    "fitted to, and prove again that every collision element lies inside a capsule of its link. "
                    "Exit status: 0 proven, 2 bad input or not contained (the link and element are named), "
                    "3 internal error.")
    v.add_argument("robot", nargs="?", metavar="ROBOT.yaml",
                   help="robot file from `larc fit-capsules` (default: PIPER's capsule file shipped in larc_jax/data/piper_capsules.yaml)")

    c = sub.add_parser("certify", help="certify trajectories against a scene", parents=common,
                       description="Exit status: 0 all certified (or --no-fail-on-uncertified), "
                                   "1 some not certified, 2 bad input or usage, 3 internal error.")
    c.add_argument("trajectories", nargs="*", metavar="TRAJ_FILE",
                   help="trajectory files: JointTrajectory / RobotTrajectory / DisplayTrajectory "
                        "YAML or JSON (e.g. the output of 'ros2 topic echo --once'), or CSV "
                        "(t, <joint>..., <joint>_vel...)")
    c.add_argument("--scene",
                   help="scene YAML {frame, boxes: [{name, min, max}]} or MoveIt .scene text (boxes); "
                        "required unless --manifest")
    c.add_argument("--method", default=METHODS[0], choices=METHODS)
    c.add_argument("--robot", help="robot file from 'larc fit-capsules' (default: PIPER)")
    spec_options(c)
    c.add_argument("--json", metavar="OUT.json", help="write per-trajectory results as JSON")
    c.add_argument("--certificate", metavar="OUT.json",
                   help="write a certificate file: the leaf cover (exact floats), parameters, rounding bounds "
                        "and SHA-256 of the robot file, meshes, scene and trajectories; check it with "
                        "'larc verify OUT.json'")
    c.add_argument("--leaves", metavar="OUT.parquet",
                   help="write the full leaf cover, one row per leaf (id, depth, index, t0, t1, "
                        "clearance_m, certified, capsule, box); .parquet or .csv by suffix")
    c.add_argument("--manifest", metavar="FILE.csv",
                   help="CSV with columns trajectory,scene (paths relative to it; optional id): certify "
                        "every row in chunks into --out, resumably")
    c.add_argument("--out", metavar="RESULTS.parquet",
                   help="with --manifest: results dataset (a folder of Parquet parts, one row per manifest row)")
    c.add_argument("--chunk-size", type=int, default=DEFAULT_CHUNK_SIZE,
                   help=f"with --manifest: rows per chunk (default {DEFAULT_CHUNK_SIZE})")
    c.add_argument("--dask", metavar="SCHEDULER",
                   help="with --manifest: run the chunks on a Dask cluster (scheduler address, e.g. "
                        "tcp://host:8786; needs larc_jax[distributed])")
    c.add_argument("--fail-on-uncertified", action=argparse.BooleanOptionalAction, default=True,
                   help="exit 1 if some trajectory is not certified (default); with "
                        "--no-fail-on-uncertified exit 0 unless the input is bad")

    r = sub.add_parser(
        "verify", parents=common, help="re-check a certificate file without JAX (NumPy float64 references)",
        description="Re-check a certificate written by 'larc certify --certificate': the hashes of the robot "
                    "file, URDF, meshes, scene and trajectories; that the leaves of every trajectory claimed "
                    "certified tile its horizon; that every such leaf passes the NumPy float64 interval test, "
                    "recomputed from the files; the pins asked. It prints every file and hash it checked and every "
                    "assumption. Exit status: 0 verified, 1 refuted (the first failing leaf or pin is named), "
                    "2 bad input, 3 internal error.")
    r.add_argument("certificate", metavar="CERT.json", help="certificate file")
    r.add_argument("--trajectory", nargs="+", metavar="FILE",
                   help="trajectory files instead of the ones the certificate names (one per trajectory, in order)")
    r.add_argument("--scene", nargs="+", metavar="FILE",
                   help="scene files instead of the ones the certificate names (one per scene, in order)")
    r.add_argument("--robot", metavar="ROBOT.yaml", help="robot file instead of the one the certificate names")
    r.add_argument("--json", action="store_true", help="the report as JSON on stdout (exit status unchanged)")
    VerifyPins.add_arguments(r)

    e = sub.add_parser(
        "explain", parents=common,
        help="certify one trajectory and draw the interval that blocks it (or its tightest one)",
        description="Certify one trajectory (LARC, with the run-spec options as for certify: enclosure, "
                    "tracking tolerance, self-collision, dtype...) and draw one leaf, decided by that whole "
                    "test: the capsules at the interval midpoint, their shells r + margin + motion radius, the "
                    "boxes (the blocking one in red; for a self-collision leaf, its two capsules), the gripper "
                    "path and every leaf's clearance. Exit status: 0 picture written (certified or not), 2 bad "
                    "input, 3 internal error.")
    e.add_argument("trajectory", metavar="TRAJ_FILE", help="one trajectory file (as for certify)")
    e.add_argument("--scene", required=True, help="scene file (as for certify)")
    e.add_argument("--robot", help="robot file from 'larc fit-capsules' (default: PIPER)")
    spec_options(e, explain=True)
    e.add_argument("--leaf", choices=["first", "worst"], default="first",
                   help="first: the first inconclusive leaf (the one certify names), or the "
                        "tightest leaf of a certified trajectory (default); worst: the leaf with "
                        "the smallest clearance")
    e.add_argument("--at", type=float, metavar="SECONDS", help="draw the leaf containing this time")
    e.add_argument("-o", "--output", metavar="OUT.png",
                   help="image to write (format from the suffix; default ID_explain.png)")
    e.set_defaults(method=METHODS[0])

    pt = sub.add_parser(
        "points", parents=common, help="convert a .pcd point cloud or an OctoMap (.bt/.ot) into scene clouds (.npy)",
        description="Write the .npy clouds a scene's `type: points` entries read, and print those entries (YAML, "
                    "with what each assumes as comments): a .pcd file's finite x, y, z points (a scene reads a .pcd "
                    "itself too; convert one to reduce it with --voxel); an OctoMap's occupied "
                    "leaves, one cloud per leaf size, each leaf a ball of radius size*sqrt(3)/2 about its centre. "
                    "Exit status: 0 written, 2 bad input, 3 internal error.")
    pt.add_argument("source", metavar="FILE", help=".pcd (needs pypcd4), .bt or .ot (needs octomap-python); "
                    ".npy or .ply only with --voxel")
    pt.add_argument("-o", "--output", required=True, metavar="OUT.npy",
                    help="cloud to write (an OctoMap with several leaf sizes: OUT_0.npy, OUT_1.npy, ...)")
    pt.add_argument("--voxel", type=float, metavar="M",
                    help="replace the points in each cube of this edge (m) by its centre, the radius grown to cover "
                         "them (fewer points, a sound but wider obstacle)")
    pt.add_argument("--name", help="obstacle name in the printed entries (default: the file's stem)")
    pt.add_argument("--unknown-in", nargs=6, type=float, metavar=("XMIN", "YMIN", "ZMIN", "XMAX", "YMAX", "ZMAX"),
                    help="OctoMap only: also make obstacles of the voxels meeting this box (m, the map's frame) that "
                         "the map holds neither occupied nor free (unknown space is otherwise not an obstacle)")

    w = sub.add_parser("view", parents=common, help="show a certificate in 3-D in the browser (viser)",
                       description="Serve an interactive 3-D view (robot along the trajectory, boxes, leaf cover, "
                                   "a leaf's enclosures) and print its URL; Ctrl-C stops it.")
    w.add_argument("inputs", nargs="+", metavar="FILE", help="a certificate (larc certify --certificate), or "
                   "trajectory files (then --scene)")
    w.add_argument("--scene", help="scene file, with trajectory files")
    w.add_argument("--robot", help="robot file, with trajectory files (default: PIPER)")
    w.add_argument("--leaves", metavar="LEAVES.csv", help="leaf table of larc certify --leaves (CSV or Parquet)")
    w.add_argument("--host", default="127.0.0.1", help="address to serve on (default 127.0.0.1; 0.0.0.0: all)")
    w.add_argument("--port", type=int, default=8080, help="port (default 8080; the next free one if taken)")
    return p
