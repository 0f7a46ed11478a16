"""The larc command line: continuous-time collision certificates for robot-arm trajectories.

Exit status: 0 success / every trajectory certified, 1 some trajectory not certified (``larc
certify`` without ``--no-fail-on-uncertified``), 2 bad input or usage (one line on stderr naming
the file, field and index), 3 internal error (a bug: traceback on stderr).

Output: tables and results on stdout; log messages (loggers ``larc`` and ``larc_jax``), progress
bars and errors on stderr. ``--quiet`` leaves only errors (and the files asked for); ``-v`` adds debug messages.
Progress bars are shown when stderr is a terminal (``--progress`` / ``--no-progress`` force).

Compiled JAX kernels are kept in a persistent cache (:mod:`larc_jax.compilation`; default
``~/.cache/larc_jax/jax``), so a second ``larc certify`` skips XLA compilation;
``--no-compile-cache`` or ``LARC_COMPILE_CACHE=0`` turn that off.
"""

from __future__ import annotations

import argparse
import logging
import sys
import traceback
from pathlib import Path

from .cli_output import PhaseTimer, logging_for, progress_bar, write_output
from .cli_parser import UsageError, build_parser as _build_parser
from ..errors import LarcInputError
from ..option_values import parse_capsules_per_link, parse_hold, parse_joints, parse_package_dirs
from ..products.report import format_clearance, leaves_bytes, leaves_format, result_json, table_lines
from ..products.verify_report import VerifyPins

log = logging.getLogger("larc")

EXIT_OK, EXIT_UNCERTIFIED, EXIT_BAD_INPUT, EXIT_INTERNAL = 0, 1, 2, 3
EXIT_REFUTED = 1
"""``larc verify``: the certificate's claim does not hold."""


def _read_trajectories(args, paths, robot):
    """Read trajectory files (progress bar over the files)."""
    from ..model.trajectory_files import read_trajectory

    kwargs = {"velocities": args.velocities} if getattr(args, "velocities", None) else {}
    out = []
    with progress_bar(args, total=len(paths), desc="reading", unit=" files") as bar:
        for p in paths:
            out.append(read_trajectory(p, robot, **kwargs))
            bar.update(1)
    log.debug("read %d trajectory files", len(out))
    return out


def _cmd_fit_capsules(args) -> int:
    from ..defaults import check_padding
    from ..enclosure.fit_robot import fit_robot_file

    with progress_bar(args, desc="fitting capsules", unit=" links") as bar:
        def on_link(msg: str) -> None:
            log.debug("%s", msg)
            bar.set_postfix_str(msg.removeprefix("fitting "), refresh=False)
            bar.update(1)

        fit = fit_robot_file(
            args.urdf, args.output, package_dirs=parse_package_dirs(args.package_dir),
            active_joints=parse_joints(args.joints), held_joint_values=parse_hold(args.hold),
            n_capsules=args.n_capsules, capsules_per_link=parse_capsules_per_link(args.capsules_per_link),
            padding_m=check_padding(args.padding, "--padding"), record_urdf=not args.no_urdf_field, progress=on_link)
    if not args.quiet:
        print("\n".join(fit.table_lines()))
    return EXIT_OK


def _cmd_verify_capsules(args) -> int:
    from ..enclosure.proof import prove_robot_file
    from ..enclosure.robot_file import default_capsule_path

    source = str(args.robot or default_capsule_path())
    with progress_bar(args, desc="verifying containment", unit=" links") as bar:
        p = prove_robot_file(args.robot, progress=lambda link: bar.update(1))  # loading checks hashes, coverage
    if not args.quiet:
        print(f"{source}: containment proven for {p.elements} collision elements of {p.links} links in "
              f"{p.capsules} capsules, {p.stated_capsules} stated-finger capsules and {p.hull_parts} hull parts "
              f"(padding {p.padding_m * 1000:g} mm; {p.seconds:.1f} s); URDF and collision geometry match the fit")
    return EXIT_OK


def _compile_cache(args, *, import_jax: bool) -> None:
    """Keep kernels and the robot's builds in the compilation cache folder
    (:func:`~larc_jax.compilation.keep_builds_in`; no JAX), and with ``import_jax`` also turn on
    JAX's persistent compilation cache there (:func:`~larc_jax.compilation.enable_compile_cache`),
    unless ``--no-compile-cache`` or ``LARC_COMPILE_CACHE=0`` say not to."""
    from ..compilation import CACHE_ENV, cache_dir_from_env, enable_compile_cache, keep_builds_in

    if not getattr(args, "compile_cache", True):
        log.debug("compilation cache: off (--no-compile-cache)")
        return
    folder = cache_dir_from_env()
    if folder is None:
        log.debug("compilation cache: off (%s=0)", CACHE_ENV)
        return
    try:
        log.debug("compilation cache: %s", (enable_compile_cache if import_jax else keep_builds_in)(folder))
    except OSError as exc:  # an unwritable cache is no reason to fail: compile instead
        log.warning("compilation cache %s unusable (%s); compiling without it", folder, exc.strerror or exc)


def _start_jax(args) -> None:
    """Import JAX once every input was read and checked: register the pytrees the readers
    deferred, and turn on the persistent compilation cache."""
    from ..lazy_jax import register_pytrees

    register_pytrees()
    _compile_cache(args, import_jax=True)


def _certify_with_progress(args, spec, trajectories, scene, robot, capsules):
    """Certify with a progress bar that says "compiling" while JAX compiles a kernel shape."""
    from ..engine.certify import certify
    from ..compilation import CompileClock

    _start_jax(args)
    n = len(trajectories)
    total = {"fine": n * 2**spec.max_depth, "coarse": n * 2**spec.coarse_depth}.get(spec.method)
    desc = f"certifying ({spec.method})"
    with progress_bar(args, total=total, desc=desc, unit=" intervals") as bar:
        def on_compile(starting: bool) -> None:
            bar.set_description_str("compiling kernels" if starting else desc)

        with CompileClock() as clock:
            try:  # what needs the robot (a tolerance's joint names, the self-skip links) is checked here
                result = certify(trajectories, scene, robot, capsules, spec=spec, progress=lambda k: bar.update(k),
                                 on_compile=on_compile)
            except LarcInputError as exc:
                raise _option_error(exc) from None
    log.debug("kernels: %d compiled or loaded, %d of them from the persistent cache; tracing %.2f s, lowering "
              "%.2f s, XLA compile or cache load %.2f s", clock.compiles, clock.cache_hits, clock.trace_s,
              clock.lower_s, clock.compile_s)
    log.debug("certified %d trajectories in %.3f s, of which %.3f s compiling (frontier per depth %s)", n,
              result.wall_time_s, result.compile_time_s, list(result.frontier_sizes))
    return result


_SPEC_OPTIONS = {"margin_m": "--margin", "padding_m": "--padding", "max_depth": "--max-depth", "tracking_tolerance": "--tracking-tolerance",
                 "self_margin_m": "--self-margin", "self_skip": "--self-skip", "ignore_links": "--ignore-link",
                 "hold": "--hold", "joints": "--joints", "dtype": "--dtype"}


def _certificate_options(args):
    """The run's :class:`~larc_jax.run_spec.RunSpec` from the certify / explain options: validated
    once, before any file is read or JAX is loaded; a bad value names its option."""
    from ..option_values import parse_tracking_tolerance
    from ..run_spec import RunSpec

    self_collision = bool(getattr(args, "self_collision", False))
    self_margin, self_skip = getattr(args, "self_margin", None), tuple(getattr(args, "self_skip", None) or ())
    if not self_collision and (self_skip or self_margin is not None):
        raise LarcInputError("--self-margin and --self-skip need --self-collision")
    tolerance = getattr(args, "tracking_tolerance", None)
    try:
        return RunSpec(method=args.method, margin_m=args.margin, max_depth=args.max_depth, enclosure=args.enclosure,
                       padding_m=getattr(args, "padding", None), swept=bool(getattr(args, "swept", False)),
                       velocities=args.velocities, dtype=args.dtype, self_collision=self_collision,
                       self_margin_m=0.0 if self_margin is None else self_margin, self_skip=self_skip,
                       tracking_tolerance=None if tolerance is None else parse_tracking_tolerance(tolerance),
                       hold=parse_hold(getattr(args, "hold", None)),
                       joints=tuple(parse_joints(getattr(args, "joints", None)) or ()),
                       ignore_links=tuple(getattr(args, "ignore_link", None) or ()))
    except LarcInputError as exc:
        raise _option_error(exc) from None


def _option_error(exc: LarcInputError) -> LarcInputError:
    """A run-spec field's error (``margin_m ...``, ``certify: margin_m ...``) naming its option instead."""
    text = str(exc).removeprefix("certify: ")
    field = next((f for f in _SPEC_OPTIONS if text.startswith(f)), None)
    return exc if field is None else LarcInputError(_SPEC_OPTIONS[field] + text[len(field):])


def _capsules_without(args, robot, capsules):
    """The capsule model without the links of ``--ignore-link`` (refused if they move)."""
    if getattr(args, "ignore_link", None):
        capsules = capsules.without_links(robot, args.ignore_link, what="--ignore-link")
    if capsules.excluded_links:
        log.debug("certificate excludes links: %s", ", ".join(capsules.excluded_links))
    return capsules


def _check_certify_options(args, outputs=()):
    """The run spec (:func:`_certificate_options`) and the output paths, checked before any file
    is read; returns the spec."""
    spec = _certificate_options(args)
    for option, out in outputs:
        if out and Path(out).is_dir():
            raise LarcInputError(f"{option} {out}: is a directory, expected a file name to write")
    _compile_cache(args, import_jax=False)  # JAX is imported once every input was read (_start_jax)
    return spec


def _cmd_certify(args) -> int:
    import json

    if args.manifest:
        return _certify_manifest(args)
    for option in ("out", "dask"):
        if getattr(args, option):
            raise LarcInputError(f"--{option} needs --manifest")
    if not args.trajectories:
        raise LarcInputError("certify needs trajectory files (TRAJ_FILE ...) or --manifest FILE.csv")
    if not args.scene:
        raise LarcInputError("certify needs --scene FILE (or --manifest FILE.csv, whose rows name the scenes)")
    spec = _check_certify_options(args, (("--json", args.json), ("--leaves", args.leaves),
                                         ("--certificate", args.certificate)))
    leaves_fmt = leaves_format(args.leaves) if args.leaves else None  # fail before the work
    from ..lazy_jax import defer_jax

    defer_jax()  # the robot, scene and trajectories are read and checked before JAX is imported
    from ..enclosure.robot_file import load_robot_file
    from ..model.scene import read_scene

    timer = PhaseTimer()
    robot, capsules = load_robot_file(args.robot, hold=dict(spec.hold), active_joints=list(spec.joints) or None)
    capsules = _capsules_without(args, robot, capsules)
    timer.lap("robot")
    scene = read_scene(args.scene, frame=robot.link_names[0])
    log.debug("scene %s: %d boxes", args.scene, scene.n_boxes)
    trajectories = _read_trajectories(args, args.trajectories, robot)
    timer.lap("read")
    result = _certify_with_progress(args, spec, trajectories, scene, robot, capsules)
    timer.lap("certify")
    timer.log(result)
    if not args.quiet:
        print("\n".join(table_lines(result)))
    if args.json:
        write_output(args.json, (json.dumps(result_json(result, args.scene), indent=2) + "\n").encode(),
                      "per-trajectory results")
    if args.leaves:
        n_leaves = sum(len(r.leaves) for r in result)
        write_output(args.leaves, leaves_bytes(result, leaves_fmt), f"{n_leaves} leaves")
    if args.certificate:
        from ..products.certificate import write_certificate

        write_certificate(args.certificate, result, trajectories, scene, robot, capsules, robot_file=args.robot,
                          trajectory_files=args.trajectories, scene_files=[args.scene], velocities=spec.velocities)
        log.info("wrote %s (certificate of %d trajectories; check it with `larc verify %s`)", args.certificate,
                 len(result), args.certificate)
    if all(r.certified for r in result):
        return EXIT_OK
    if not args.fail_on_uncertified:
        log.info("some trajectories are not certified; exit status 0 (--no-fail-on-uncertified)")
        return EXIT_OK
    return EXIT_UNCERTIFIED


def _certify_manifest(args) -> int:
    """``larc certify --manifest``: chunks into a resumable Parquet dataset (larc_jax.drivers.manifest)."""
    from .manifest import ManifestJob, certify_manifest

    if args.trajectories or args.scene:
        raise LarcInputError("--manifest takes the trajectories and scenes from its rows: "
                             "give no TRAJ_FILE and no --scene")
    if args.json:
        raise LarcInputError("--json is not available with --manifest (the results go to --out)")
    if args.certificate:
        raise LarcInputError("--certificate is not available with --manifest")
    if not args.out:
        raise LarcInputError("--manifest needs --out RESULTS.parquet (a folder of Parquet parts)")
    spec = _check_certify_options(args)
    _start_jax(args)
    job = ManifestJob(out=args.out, leaves=args.leaves, robot_file=args.robot, spec=spec, chunk_size=args.chunk_size)
    rows_done = [0]
    with progress_bar(args, desc=f"certifying ({spec.method})", unit=" intervals") as bar:

        def on_chunk(summary: dict) -> None:
            if args.dask:  # workers cannot report intervals as they go: count per chunk
                bar.update(summary["evaluations"])
            rows_done[0] += summary["rows"]
            bar.set_postfix_str(f"{rows_done[0]} rows", refresh=False)
            if summary["first_error"]:
                log.warning("%s", summary["first_error"])

        if args.dask:
            from .distributed import certify_manifest_dask

            total = certify_manifest_dask(args.manifest, job, args.dask, on_chunk=on_chunk)
        else:
            total = certify_manifest(args.manifest, job, on_chunk=on_chunk, progress=bar.update)
    import pandas as pd

    parts = sorted(Path(args.out).glob("part-*.parquet"))
    results = pd.read_parquet(args.out, columns=["certified", "error"]) if parts else \
        pd.DataFrame({"certified": [], "error": []})
    n, n_ok, n_err = len(results), int(results["certified"].sum()), int((results["error"] != "").sum())
    if not args.quiet:
        print(f"{n_ok} of {n} certified, {n_err} bad input ({spec.method}, margin {spec.margin_m * 1000:g} mm); "
              f"{total['chunks_done']} chunks now, {total['chunks_skipped']} already done; results in {args.out}"
              + (f", leaves in {args.leaves}" if args.leaves else ""))
    if n_err:
        log.error("%d manifest rows are bad input (the error column of %s says why)", n_err, args.out)
        return EXIT_BAD_INPUT
    if n_ok == n or not args.fail_on_uncertified:
        return EXIT_OK
    return EXIT_UNCERTIFIED


def _check_image_path(path: Path) -> None:
    try:
        from matplotlib.backend_bases import FigureCanvasBase
    except ImportError:
        raise LarcInputError("larc explain needs matplotlib (pip install matplotlib)") from None
    kinds = FigureCanvasBase.get_supported_filetypes()
    if path.suffix.lower().lstrip(".") not in kinds:
        raise LarcInputError(f"{path}: unknown image type '{path.suffix}' (use one of: "
                             f"{', '.join('.' + k for k in sorted(kinds))})")


def _cmd_explain(args) -> int:
    from ..enclosure.robot_file import load_robot_file
    from ..products.explain import choose_leaf, describe_leaf, explain, render
    from ..model.scene import read_scene

    out = Path(args.output) if args.output else None
    spec = _check_certify_options(args, (("--output", args.output),))
    _check_image_path(out or Path("x.png"))  # fail before the work
    _start_jax(args)
    robot, capsules = load_robot_file(args.robot, hold=dict(spec.hold), active_joints=list(spec.joints) or None)
    capsules = _capsules_without(args, robot, capsules)
    scene = read_scene(args.scene, frame=robot.link_names[0])
    (traj,) = _read_trajectories(args, [args.trajectory], robot)
    result = _certify_with_progress(args, spec, [traj], scene, robot, capsules)[0]
    leaf = choose_leaf(result, args.leaf, at=args.at)
    ex = explain(robot, capsules, traj, scene, result, leaf=leaf)
    out = out or Path(f"{result.id}_explain.png")
    try:
        render(ex, robot, capsules, traj, scene, result, out)
    except OSError as exc:
        raise LarcInputError(f"{out}: cannot write the picture ({exc.strerror or exc})") from None
    if not args.quiet:
        status = "CERTIFIED" if result.certified else "UNCERTIFIED"
        pair = f"capsules {leaf.capsule} / {leaf.other_capsule}" if leaf.other_capsule else \
            f"capsule {leaf.capsule} / box {leaf.box}" if leaf.box else "no boxes"
        decided = f", passed by the {ex.stage} test" if ex.stage else ""
        print(f"{result.id}: {status}; {describe_leaf(result, leaf)}: t=[{leaf.t0:.4f}, {leaf.t1:.4f}] s "
              f"(depth {leaf.depth}), {pair}, clearance {format_clearance(leaf.clearance_m)}{decided}")
        if ex.capsule >= 0 and ex.box >= 0:
            c = ex.capsule
            print(f"  axis-to-box distance {ex.distance_m * 1000:.2f} mm vs shell r + margin + motion "
                  f"= {ex.radius[c] * 1000:.2f} + {ex.margin_m * 1000:.2f} + {ex.motion_b[c] * 1000:.2f} mm")
    log.info("wrote %s", out)
    return EXIT_OK


def _cmd_verify(args) -> int:
    import json

    from ..products.verify import Refuted, verify_certificate  # NumPy only: this process never loads JAX
    from ..products.verify_report import input_error_json, report_json, report_lines

    status = EXIT_OK
    try:
        report = verify_certificate(args.certificate, trajectories=args.trajectory, scenes=args.scene,
                                    robot=args.robot, pins=VerifyPins.from_namespace(args))
    except Refuted as exc:
        print(f"larc: REFUTED: {args.certificate}: {exc}", file=sys.stderr)
        report, status = exc.report, EXIT_REFUTED
    except LarcInputError as exc:
        if args.json:
            print(json.dumps(input_error_json(args.certificate, str(exc)), indent=1))
        raise
    if report is not None and args.json:
        print(json.dumps(report_json(report), indent=1))
    elif report is not None and not args.quiet:
        print("\n".join(report_lines(report)))
    return status


def _cmd_points(args) -> int:
    import json

    from ..model.sensor_files import convert_sensor_file  # NumPy and the file's reader: never JAX

    entries = convert_sensor_file(args.source, args.output, voxel_m=args.voxel, name=args.name,
                                  unknown_in=args.unknown_in)
    if not args.quiet:
        lines = [f"# {args.source}: {note}" for e in entries for note in e["notes"]]
        lines += ["# file: make it relative to the scene file; add a pose if the cloud is not in the scene's frame",
                  "obstacles:"]
        lines += [f"  - {{name: {json.dumps(e['name'])}, type: points, file: {json.dumps(e['file'])}, "
                  f"radius: {e['radius']!r}}}" for e in entries]  # JSON strings: valid YAML scalars
        print("\n".join(lines))
    for e in entries:
        log.info("wrote %s", e["file"])
    return EXIT_OK


def _cmd_view(args) -> int:
    from ..products.view import view_command  # NumPy and viser: this process never loads JAX

    return view_command(args)


def build_parser() -> argparse.ArgumentParser:
    """The ``larc`` argument parser (:mod:`larc_jax.drivers.cli_parser`)."""
    return _build_parser(description=__doc__.splitlines()[0])


_COMMANDS = {"fit-capsules": _cmd_fit_capsules, "verify-capsules": _cmd_verify_capsules, "certify": _cmd_certify,
             "verify": _cmd_verify, "explain": _cmd_explain, "view": _cmd_view, "points": _cmd_points}


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    try:
        args = parser.parse_args(argv)
    except UsageError as exc:
        print(f"larc: error: {exc}", file=sys.stderr)
        return EXIT_BAD_INPUT
    with logging_for(args):
        try:
            return _COMMANDS[args.command](args)
        except LarcInputError as exc:
            print(f"larc: error: {exc}", file=sys.stderr)
            return EXIT_BAD_INPUT
        except Exception:  # noqa: BLE001 - a bug: exit 3, never 1 (which means "not certified")
            traceback.print_exc(file=sys.stderr)
            print("larc: internal error (a bug; the traceback is above)", file=sys.stderr)
            return EXIT_INTERNAL


if __name__ == "__main__":
    sys.exit(main())
