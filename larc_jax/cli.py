"""The ``larc`` command line.

Exit status: 0 success / every trajectory certified, 1 some trajectory not certified,
2 bad input (one line on stderr naming the file, field and index).
"""

from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path

from .errors import LarcInputError

log = logging.getLogger("larc")

EXIT_OK, EXIT_UNCERTIFIED, EXIT_BAD_INPUT = 0, 1, 2


def _package_dirs(items: list[str] | None) -> dict[str, str]:
    out = {}
    for item in items or []:
        name, sep, path = item.partition("=")
        if not sep or not name or not path:
            raise LarcInputError(f"--package-dir '{item}': expected NAME=PATH")
        out[name] = path
    return out


def _cmd_fit_capsules(args) -> int:
    from .capsules import fit_capsules, load_capsules, save_capsules, verify_containment
    from .robot import load_robot

    per_link = {}
    for item in args.capsules_per_link or []:
        link, sep, count = item.partition("=")
        if not sep or not count.isdigit():
            raise LarcInputError(f"--capsules-per-link '{item}': expected LINK=1 or LINK=2")
        per_link[link] = int(count)
    held = {}
    for item in args.hold or []:
        joint, sep, value = item.partition("=")
        try:
            held[joint] = float(value)
        except ValueError:
            raise LarcInputError(f"--hold '{item}': expected JOINT=VALUE") from None
    robot = load_robot(
        args.urdf, _package_dirs(args.package_dir),
        active_joints=args.joints.split(",") if args.joints else None,
        held_joint_values=held,
    )
    fitted = fit_capsules(
        robot, n_capsules=args.n_capsules, capsules_per_link=per_link, padding_m=args.padding,
        progress=None if args.quiet else (lambda msg: print(msg, file=sys.stderr)),
    )
    urdf_field = None if args.no_urdf_field else str(Path(args.urdf))
    save_capsules(args.output, robot, fitted, padding_m=args.padding, urdf=urdf_field)
    caps = load_capsules(args.output, robot)
    checked = verify_containment(robot, caps, source=str(args.output))
    if not args.quiet:
        print(f"{'capsule':<12} {'link':<10} {'radius_m':>9} {'vol_cm3':>8} {'hull_cm3':>8} {'ratio':>6}")
        for f in fitted:
            print(f"{f.name:<12} {f.link:<10} {f.radius:>9.6f} {f.volume_m3 * 1e6:>8.1f} "
                  f"{f.hull_volume_m3 * 1e6:>8.1f} {f.volume_m3 / max(f.hull_volume_m3, 1e-30):>6.2f}")
        print(f"wrote {args.output}: {len(fitted)} capsules; containment proven for "
              f"{sum(checked.values())} mesh elements")
    return EXIT_OK


def _load_model(args):
    """Robot + capsules: ``--robot FILE`` (a capsule file with a ``urdf`` field) or PIPER."""
    import yaml

    from .capsules import default_capsule_path, load_capsules
    from .robot import load_robot

    if args.robot:
        path = Path(args.robot)
        try:
            doc = yaml.safe_load(path.read_text())
        except FileNotFoundError:
            raise LarcInputError(f"{path}: robot file does not exist") from None
        except yaml.YAMLError as exc:
            raise LarcInputError(f"{path}: not valid YAML ({exc})".replace("\n", " ")) from None
        if not isinstance(doc, dict) or "urdf" not in doc:
            raise LarcInputError(f"{path}: missing field 'urdf' (write it with `larc fit-capsules URDF -o FILE`)")
        urdf = Path(doc["urdf"])
        if not urdf.is_absolute():
            urdf = path.parent / urdf
        robot = load_robot(urdf, doc.get("package_dirs"), active_joints=doc.get("active_joints"),
                           held_joint_values=doc.get("held_joints"))
        return robot, load_capsules(path, robot)
    robot = load_robot()
    return robot, load_capsules(default_capsule_path(), robot)


def _fmt_clearance(g: float) -> str:
    if g != g:
        return "nan"
    if g == float("inf"):
        return "inf (no boxes)"
    return f"{g * 1000:+.2f} mm"


def _cmd_certify(args) -> int:
    import json
    import math

    from .certify import certify
    from .io import atomic_write_text
    from .scene import read_scene
    from .trajectory import read_trajectory

    robot, capsules = _load_model(args)
    scene = read_scene(args.scene, frame=robot.link_names[0])
    trajectories = [read_trajectory(p, robot) for p in args.trajectories]
    result = certify(trajectories, scene, robot, capsules, method=args.method, margin=args.margin,
                     max_depth=args.max_depth)
    if not args.quiet:
        print(f"{'trajectory':<28} {'status':<12} {'evals':>6} {'min clearance':>15}  blocked by")
        for r in result:
            bad = r.first_inconclusive
            blocked = (f"t=[{bad.t0:.4f}, {bad.t1:.4f}] s  {bad.capsule} / {bad.box}" if bad else "")
            print(f"{r.id:<28} {'CERTIFIED' if r.certified else 'UNCERTIFIED':<12} {r.evaluations:>6} "
                  f"{_fmt_clearance(r.min_clearance_m):>15}  {blocked}")
    if args.json:
        def num(x):
            return x if math.isfinite(x) else None

        doc = {
            "method": result.method, "margin_m": result.margin_m, "max_depth": result.max_depth,
            "scene": str(args.scene),
            "frontier_sizes": list(result.frontier_sizes),
            "trajectories": [
                {"id": r.id, "certified": r.certified, "evaluations": r.evaluations,
                 "frontier_sizes": list(r.frontier_sizes), "min_clearance_m": num(r.min_clearance_m),
                 "first_inconclusive": (
                     {"t0": r.first_inconclusive.t0, "t1": r.first_inconclusive.t1,
                      "capsule": r.first_inconclusive.capsule, "box": r.first_inconclusive.box,
                      "clearance_m": num(r.first_inconclusive.clearance_m)}
                     if r.first_inconclusive else None)}
                for r in result
            ],
        }
        atomic_write_text(args.json, json.dumps(doc, indent=2) + "\n")
    return EXIT_OK if all(r.certified for r in result) else EXIT_UNCERTIFIED


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="larc", description=__doc__.splitlines()[0])
    p.add_argument("--quiet", "-q", action="store_true", help="no progress output")
    p.add_argument("--verbose", "-v", action="store_true", help="debug logging")
    sub = p.add_subparsers(dest="command", required=True)

    f = sub.add_parser("fit-capsules", help="fit proven capsules to a URDF's collision meshes")
    f.add_argument("urdf", help="URDF file")
    f.add_argument("-o", "--output", required=True, help="capsule YAML to write")
    f.add_argument("--package-dir", action="append", metavar="NAME=PATH",
                   help="folder of a ROS package named in package:// mesh URIs (repeatable)")
    f.add_argument("--capsules-per-link", action="append", metavar="LINK=N",
                   help="force 1 or 2 capsules on a link (repeatable)")
    f.add_argument("--n-capsules", type=int, default=None,
                   help="total capsule count: links that gain most from a split get two")
    f.add_argument("--padding", type=float, default=0.001, help="padding added to radii, m")
    f.add_argument("--joints", help="comma-separated active joints (default: the trunk chain)")
    f.add_argument("--hold", action="append", metavar="JOINT=VALUE",
                   help="value at which a non-active joint is held (repeatable)")
    f.add_argument("--no-urdf-field", action="store_true",
                   help="do not record the URDF path in the file (e.g. for PIPER, found via env)")
    f.set_defaults(func=_cmd_fit_capsules)

    c = sub.add_parser("certify", help="certify trajectories against a scene",
                       description="Exit status: 0 all certified, 1 some not certified, 2 bad input.")
    c.add_argument("trajectories", nargs="+", metavar="TRAJ_FILE",
                   help="JointTrajectory YAML/JSON files (joint_names, points with positions, "
                        "velocities, time_from_start)")
    c.add_argument("--scene", required=True, help="scene YAML: {frame, boxes: [{name, min, max}]}")
    c.add_argument("--method", default="larc", choices=["larc", "fine", "coarse", "reference"])
    c.add_argument("--margin", type=float, default=0.01, help="clearance margin rho, m (default 0.01)")
    c.add_argument("--max-depth", type=int, default=9, help="maximum bisection depth (default 9)")
    c.add_argument("--robot", help="robot file from `larc fit-capsules` (default: PIPER)")
    c.add_argument("--json", metavar="OUT.json", help="write per-trajectory results as JSON")
    c.set_defaults(func=_cmd_certify)
    return p


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    logging.basicConfig(
        level=logging.DEBUG if args.verbose else (logging.WARNING if args.quiet else logging.INFO),
        format="%(levelname)s %(name)s: %(message)s",
    )
    logging.getLogger("jax").setLevel(logging.WARNING)  # backend probing noise
    try:
        return args.func(args)
    except LarcInputError as exc:
        print(f"larc: error: {exc}", file=sys.stderr)
        return EXIT_BAD_INPUT


if __name__ == "__main__":
    sys.exit(main())
