"""What ``larc verify`` established and assumed, and the pins a caller holds it to.

:func:`~larc_jax.products.verify.verify_certificate` returns a :class:`VerifyReport` (and a
:class:`Refuted` carries the one built up to the refutation): the files it read, each with where
its name came from (``supplied``: the caller gave it, ``--robot``/``--scene``/``--trajectory``;
``certificate``: the certificate names it; ``shipped``: PIPER's robot file, which a certificate
names by ``null``) and the SHA-256 of the bytes read; the parameters, which always come from the
certificate (margin, depth, enclosure, padding, geometry dtype, excluded links, tracking tolerance, the
self-collision margin and the pairs not checked); the robot's held joints and which of them were
stated; per trajectory its velocity mode. :func:`report_lines` formats it for people,
:func:`report_json` for machines (``larc verify --json``).

A :class:`VerifyPins` holds the certificate to what the caller requires (CLI flag = field name
with ``-`` for ``_`` and without ``_m``: ``margin_at_least_m`` is ``--margin-at-least``); a
certificate that does not meet a pin is refuted, naming the pin. ``allow_finite_difference`` is
a permission, not a pin (:mod:`larc_jax.products.verify`, "velocities").

This module imports no JAX (``larc verify`` never loads it).
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import re
from pathlib import Path

from ..defaults import ENCLOSURES, VELOCITY_MODES, check_depth, check_margin, check_padding
from ..errors import LarcInputError, OneLineError, one_line
from ..run_spec import DTYPES, RunSpec

__all__ = ["Refuted", "VerifyPins", "VerifyReport", "InputFile", "SceneFacts", "TrajectoryFacts", "RobotFacts",
           "Parameters", "report_lines", "report_json", "input_error_json"]


class Refuted(OneLineError):
    """The certificate's claim does not hold (the message names the trajectory, leaf, file or pin
    and why). ``report``: what the checker had established before (set by ``verify_certificate``)."""

    report: "VerifyReport | None" = None


@dataclasses.dataclass(frozen=True)
class InputFile:
    """A file the checker read and where its name came from."""

    path: str
    source: str
    """``supplied`` (by the caller), ``certificate`` (named by it) or ``shipped`` (PIPER's robot file)."""
    sha256: str
    """Of the bytes read now."""
    recorded_sha256: str | None
    """What the certificate records for the file (``None``: certified from arrays through the API)."""


@dataclasses.dataclass(frozen=True)
class SceneFacts:
    index: int
    file: InputFile
    arrays_sha256: str
    boxes: tuple[str, ...]
    """Names of the obstacles read, boxes then posed shapes (none: the certificate claims nothing
    about obstacles)."""
    assumes: tuple[str, ...] = ()
    """What the claim assumes of each mesh, cloud and plane (:meth:`~larc_jax.model.scene.Scene.assumptions`)."""


@dataclasses.dataclass(frozen=True)
class TrajectoryFacts:
    id: str
    claimed: bool
    """Claimed certified (only these are read and re-checked)."""
    scene: int
    velocities: str
    """The velocity mode the certificate records (``recorded`` when it records none)."""
    file: InputFile | None = None
    """``None``: not read (not claimed certified)."""
    arrays_sha256: str | None = None
    ignored_velocities: int = 0
    """Waypoints whose recorded velocities the finite-difference reading ignored."""
    leaves: int = 0
    """Leaves re-checked."""


@dataclasses.dataclass(frozen=True)
class RobotFacts:
    file: InputFile
    urdf: str
    urdf_sha256: str
    geometry: tuple[tuple[str, str, str | None], ...]
    """(link, mesh URI or primitive, mesh SHA-256 or None) per collision element checked."""
    active_joints: tuple[str, ...]
    held_joints: tuple[tuple[str, float, bool], ...]
    """(joint, value, stated): a stated joint's links are enclosed at the value alone, the others over their
    stroke, except the :attr:`fixed_joints`."""
    capsules: int
    excluded_links: tuple[tuple[str, str], ...]
    """(link, ``robot file`` or ``certificate``): links not checked at all."""
    fixed_joints: tuple[str, ...] = ()
    """Held joints neither stated nor enclosed over a stroke (a revolute joint the robot file
    holds): their links are placed at the held value alone, so the claim assumes they never move."""


@dataclasses.dataclass(frozen=True)
class Parameters:
    """The run's parameters as the report shows them: the certificate's
    :class:`~larc_jax.run_spec.RunSpec` (:meth:`of`), with what the robot decides filled in once
    it is loaded."""

    method: str
    margin_m: float
    max_depth: int
    dtype: str
    enclosure: str
    excluded_links: tuple[str, ...]
    padding_m: float
    """Padding on every enclosure beyond its proven containment of the link meshes, m."""
    tracking_tolerance: float | tuple | None
    """As the spec states it; once the robot is loaded, (active joint, delta_j) per joint."""
    self_margin_m: float | None
    """``None``: self-collision not certified."""
    self_skip: tuple[str, ...] = ()
    """``LINK:LINK`` pairs the user skipped."""
    self_not_checked: tuple[tuple[str, str, str], ...] = ()
    """Every link pair the self test does not check, with why (set once the robot is loaded)."""
    velocities: str = VELOCITY_MODES[0]
    swept: bool = False
    """Whether the swept stage (:mod:`larc_jax.leaf.swept`) was part of the test."""

    @classmethod
    def of(cls, spec: RunSpec) -> "Parameters":
        return cls(method=spec.method, margin_m=spec.margin_m, max_depth=spec.max_depth, dtype=spec.dtype,
                   enclosure=spec.enclosure, excluded_links=spec.ignore_links, padding_m=spec.padding_m,
                   tracking_tolerance=spec.tracking_tolerance,
                   self_margin_m=spec.self_margin_m if spec.self_collision else None, self_skip=spec.self_skip,
                   velocities=spec.velocities, swept=spec.swept)


@dataclasses.dataclass(frozen=True)
class VerifyReport:
    trajectories: int = 0
    """Trajectories in the certificate."""
    checked: int = 0
    """Of them, claimed certified and re-checked."""
    leaves: int = 0
    """Leaves re-checked."""
    max_clearance_diff_m: float = 0.0
    """Largest |stored clearance - recomputed clearance| over the re-checked leaves, m."""
    min_excess_m: float = math.inf
    """Smallest recomputed ``g - guard`` over the re-checked leaves, m (> 0)."""
    certificate: str = ""
    refuted: str | None = None
    """The refutation (``None``: verified); the other fields then hold what was established before it."""
    parameters: Parameters | None = None
    robot: RobotFacts | None = None
    scene_files: tuple[SceneFacts, ...] = ()
    trajectory_files: tuple[TrajectoryFacts, ...] = ()
    pins: tuple[str, ...] = ()
    """The pins asked (as CLI flags); all held unless ``refuted`` names one."""
    allow_finite_difference: bool = False


def _flag(field: str) -> str:
    return "--" + re.sub(r"_m$", "", field).replace("_", "-")


def _pin(field: str, value) -> str:
    """A pin as its CLI flag and value."""
    if value is True:
        return _flag(field)
    shown = ",".join(f"{j}={x!r}" for j, x in value.items()) if isinstance(value, dict) else str(value)
    return f"{_flag(field)} {shown}"


@dataclasses.dataclass(frozen=True)
class VerifyPins:
    """What the caller requires of a certificate beyond its own claim (module docstring)."""

    margin_at_least_m: float | None = None
    """rho >= this, m."""
    padding_at_least_m: float | None = None
    """The padding on every enclosure >= this, m."""
    depth_at_most: int | None = None
    """maximum depth <= this."""
    velocities: str | None = None
    """Every trajectory claimed certified was read with this velocity mode."""
    enclosure: str | None = None
    dtype: str | None = None
    """Geometry dtype."""
    no_excluded_links: bool = False
    """No link left out (by the certificate or the robot file)."""
    tracking_tolerance_at_least: object = None
    """Per active joint, the tolerance >= this: a number (every joint), a mapping joint -> number or
    the CLI text ``RAD|JOINT=V,...`` (joints not named: no requirement)."""
    self_collision: bool = False
    """Self-collision certified."""
    self_margin_at_least_m: float | None = None
    """Self-collision certified with at least this margin, m."""
    no_self_skip: bool = False
    """Self-collision certified without user-skipped link pairs."""
    no_stated_joints: bool = False
    """No held joint stated (the gripper enclosed over its whole stroke, valid at any opening)."""
    robot_sha256: str | None = None
    """The robot file's bytes have this SHA-256 (it records the URDF's and every mesh's)."""
    all_certified: bool = False
    """Every trajectory the certificate names is claimed certified (so re-checked): a trajectory
    marked not certified is otherwise skipped, and its file, even one supplied, is not read."""
    require_files: bool = False
    """Every scene and trajectory claimed certified is a file the caller supplied or one the
    certificate names with its file hash (not bound by its arrays alone)."""
    allow_finite_difference: bool = False
    """Accept a trajectory certified with finite-difference velocities although its file records
    velocities (a permission; :mod:`larc_jax.products.verify`)."""

    def __post_init__(self):
        f = _flag
        if self.margin_at_least_m is not None:
            check_margin(self.margin_at_least_m, f("margin_at_least_m"))
        if self.padding_at_least_m is not None:
            check_padding(self.padding_at_least_m, f("padding_at_least_m"))
        if self.self_margin_at_least_m is not None:
            from ..leaf.self_collision import check_self_margin  # after larc_jax.products.verify deferred JAX

            check_self_margin(self.self_margin_at_least_m, f("self_margin_at_least_m"))
        if self.depth_at_most is not None:
            check_depth(self.depth_at_most, f("depth_at_most"))
        for name, allowed in (("velocities", VELOCITY_MODES), ("enclosure", ENCLOSURES), ("dtype", DTYPES)):
            value = getattr(self, name)
            if value is not None and value not in allowed:
                raise LarcInputError(f"{f(name)} {value!r}: one of {', '.join(allowed)}")
        if self.robot_sha256 is not None:
            if not re.fullmatch(r"[0-9a-fA-F]{64}", str(self.robot_sha256)):
                raise LarcInputError(f"{f('robot_sha256')} {str(self.robot_sha256)[:80]!r}: expected 64 hex digits")
            object.__setattr__(self, "robot_sha256", str(self.robot_sha256).lower())
        if isinstance(self.tracking_tolerance_at_least, str):
            from ..enclosure.tracking import parse_tracking_tolerance

            object.__setattr__(self, "tracking_tolerance_at_least", parse_tracking_tolerance(
                self.tracking_tolerance_at_least, f("tracking_tolerance_at_least")))

    @classmethod
    def add_arguments(cls, parser: argparse.ArgumentParser) -> None:
        """Declare the pins as options of ``larc verify`` (their flags are the field names)."""
        g = parser.add_argument_group("pins (a certificate that does not meet one is refuted, naming it) and "
                                      "--allow-finite-difference")
        helps = {"margin_at_least_m": ("M", float, "margin rho >= M, m"),
                 "padding_at_least_m": ("M", float, "padding on every enclosure >= M, m"),
                 "depth_at_most": ("D", int, "maximum bisection depth <= D"),
                 "velocities": ("MODE", VELOCITY_MODES,
                                "every trajectory claimed certified read with this velocity mode"),
                 "enclosure": ("E", ENCLOSURES, "certified with this enclosure"),
                 "dtype": ("DTYPE", DTYPES, "certified with this geometry dtype"),
                 "tracking_tolerance_at_least": ("RAD|JOINT=V,...", str,
                                                 "tracking tolerance at least this per active joint"),
                 "self_margin_at_least_m": ("M", float, "self-collision certified with margin >= M, m"),
                 "robot_sha256": ("HEX", str, "the robot file's SHA-256")}
        for field in dataclasses.fields(cls):
            if field.name in helps:
                metavar, kind, text = helps[field.name]
                choices = kind if isinstance(kind, tuple) else None
                g.add_argument(_flag(field.name), dest=field.name, metavar=None if choices else metavar,
                               type=None if choices else kind, choices=choices, help=text)
            else:
                g.add_argument(_flag(field.name), dest=field.name, action="store_true", help=_BOOL_HELP[field.name])

    @classmethod
    def from_namespace(cls, args) -> "VerifyPins":
        return cls(**{f.name: getattr(args, f.name) for f in dataclasses.fields(cls) if hasattr(args, f.name)})

    def asked(self) -> tuple[str, ...]:
        out = []
        for field in dataclasses.fields(self):
            value = getattr(self, field.name)
            if field.name != "allow_finite_difference" and value is not None and value is not False:
                out.append(_pin(field.name, value))
        return tuple(out)

    def _refute(self, field: str, why: str):
        raise Refuted(f"pin {_pin(field, getattr(self, field))}: {why}")

    def check_parameters(self, spec: RunSpec) -> None:
        """The pins on the certificate's run spec (before any file is read)."""
        if self.margin_at_least_m is not None and not spec.margin_m >= self.margin_at_least_m:
            self._refute("margin_at_least_m", f"the certificate's margin is {spec.margin_m!r} m")
        if self.padding_at_least_m is not None and not spec.padding_m >= self.padding_at_least_m:
            self._refute("padding_at_least_m", f"the certificate's padding is {spec.padding_m!r} m")
        if self.depth_at_most is not None and spec.max_depth > self.depth_at_most:
            self._refute("depth_at_most", f"the certificate's maximum depth is {spec.max_depth}")
        for name in ("enclosure", "dtype"):
            if getattr(self, name) is not None and getattr(spec, name) != getattr(self, name):
                self._refute(name, f"the certificate's {name} is {getattr(spec, name)}")
        if self.no_excluded_links and spec.ignore_links:
            self._refute("no_excluded_links", f"the certificate leaves out {', '.join(spec.ignore_links)}")
        wants_self = self.self_collision or self.self_margin_at_least_m is not None or self.no_self_skip
        if wants_self and not spec.self_collision:
            asked = [n for n in ("self_collision", "self_margin_at_least_m", "no_self_skip")
                     if getattr(self, n) is not None and getattr(self, n) is not False]
            self._refute(asked[0], "the certificate does not certify self-collision")
        if self.self_margin_at_least_m is not None and not spec.self_margin_m >= self.self_margin_at_least_m:
            self._refute("self_margin_at_least_m",
                         f"the certificate's self-collision margin is {spec.self_margin_m!r} m")
        if self.no_self_skip and spec.self_skip:
            self._refute("no_self_skip", f"the certificate skips the pairs {', '.join(spec.self_skip)}")

    def check_robot(self, r: RobotFacts, robot, delta) -> None:
        """The pins on the robot file (``robot``: the loaded Robot; ``delta``: the certificate's
        tracking tolerance per active joint, or None)."""
        if self.robot_sha256 is not None and r.file.sha256 != self.robot_sha256:
            self._refute("robot_sha256", f"the robot file {r.file.path} has sha256 {r.file.sha256}")
        stated = [j for j, _, s in r.held_joints if s]
        if self.no_stated_joints and stated:
            self._refute("no_stated_joints",
                         f"the certificate states {', '.join(stated)} (certified at that value alone)")
        if self.no_excluded_links and r.excluded_links:
            self._refute("no_excluded_links", "the robot file leaves out " + ", ".join(x for x, _ in r.excluded_links))
        if self.tracking_tolerance_at_least is not None:
            import numpy as np

            from ..enclosure.tracking import check_tracking_tolerance

            want = check_tracking_tolerance(self.tracking_tolerance_at_least, robot,
                                            _flag("tracking_tolerance_at_least"))
            have = np.zeros_like(want) if delta is None else np.asarray(delta, np.float64)
            short = [f"{j} {float(h)!r} < {float(w)!r}"
                     for j, h, w in zip(robot.active_joint_names, have, want) if not h >= w]
            if short:
                self._refute("tracking_tolerance_at_least", "the certificate's tolerance is " + ", ".join(short))

    def check_input(self, what: str, f: InputFile) -> None:
        if self.require_files and f.source == "certificate" and f.recorded_sha256 is None:
            self._refute("require_files", f"{what} {f.path} is named by the certificate without its file hash "
                                          "(bound by its arrays alone)")

    def check_claimed(self, tid: str) -> None:
        """A trajectory the certificate does not claim certified."""
        if self.all_certified:
            self._refute("all_certified", f"trajectory {tid!r} is not claimed certified (not checked)")

    def check_velocities(self, tid: str, mode: str) -> None:
        if self.velocities is not None and mode != self.velocities:
            self._refute("velocities", f"trajectory '{tid}' was certified with {mode} velocities")


_BOOL_HELP = {
    "no_excluded_links": "no link left out (by the certificate or its robot file)",
    "no_stated_joints": "no held joint stated (the gripper certified at any opening, not at one stated with --hold)",
    "self_collision": "self-collision certified",
    "no_self_skip": "self-collision certified without user-skipped link pairs",
    "all_certified": "every trajectory of the certificate claimed certified (one marked not certified is not checked)",
    "require_files": "every scene and trajectory checked is a file given here or one the certificate names with "
                     "its file hash",
    "allow_finite_difference": "accept a trajectory certified with finite-difference velocities although its file "
                               "records velocities (the certificate then covers a different motion; refused by default)",
}


def _file_line(f: InputFile) -> str:
    given = {"supplied": "given by the caller", "certificate": "named by the certificate",
             "shipped": "PIPER's shipped file; the certificate names none"}[f.source]
    recorded = "" if f.recorded_sha256 is not None else " (the certificate records no file hash: its arrays bind it)"
    return f"{f.path} ({given}) sha256 {f.sha256}{recorded}"


def _m(x: float | None) -> str:
    return "none" if x is None else f"{x!r} m"  # exact: a rounded margin could hide one below a pin


def _tolerance_text(tol) -> str:
    if tol is None:
        return "none (the planned curve only)"
    if not isinstance(tol, tuple):
        return f"{tol!r} for every active joint"
    return ", ".join(f"{x[0]} {x[1]!r}" if isinstance(x, tuple) else f"joint {i} {x!r}" for i, x in enumerate(tol))


def _parameter_lines(p: Parameters) -> list[str]:
    out = [f"  parameters (from the certificate's run spec): method {p.method}, margin {_m(p.margin_m)}, maximum "
           f"depth {p.max_depth}, enclosure {p.enclosure}{' + swept stage' if p.swept else ''}, "
           f"padding {_m(p.padding_m)}, geometry dtype {p.dtype}, velocities {p.velocities}",
           "  tracking tolerance: " + _tolerance_text(p.tracking_tolerance)]
    if p.self_margin_m is None:
        out.append("  self-collision: not certified")
    else:
        why: dict[str, list[str]] = {}
        for a, b, w in p.self_not_checked:
            why.setdefault(w, []).append(f"{a}:{b}")
        skipped = "; ".join(f"{w}: {', '.join(v)}" for w, v in why.items()) or "none"
        out.append(f"  self-collision: margin {_m(p.self_margin_m)}; link pairs not checked: {skipped}")
    return out


def _robot_lines(r: RobotFacts) -> list[str]:
    def how(j: str, stated: bool) -> str:
        if stated:
            return "stated: certified at this value alone, an assumption about the real joint"
        if j in r.fixed_joints:
            return "held by the robot file: its links placed at this value alone, assumed never to move"
        return "not stated: its links enclosed over the stroke"

    held = ", ".join(f"{j} = {v!r} ({how(j, s)})" for j, v, s in r.held_joints) or "none"
    out = [f"  robot file: {_file_line(r.file)}", f"  URDF: {r.urdf} sha256 {r.urdf_sha256} (assumed to describe the real robot: nothing "
           "checks that; the robot file's hash, --robot-sha256, binds this URDF and every mesh)",
           f"  active joints: {', '.join(r.active_joints)}; held joints: {held}; {r.capsules} capsules",
           "  excluded links (not checked at all): " + (", ".join(f"{x} (by the {w})" for x, w in r.excluded_links)
                                                         or "none")]
    out += [f"  collision {link}: {what}" + (f" sha256 {h}" if h else "") for link, what, h in r.geometry]
    return out


def _trajectory_line(t: TrajectoryFacts, scenes: dict[int, SceneFacts]) -> str:
    head = f"  trajectory {t.id!r}"  # quoted as Python does: an id cannot close its quote and mimic the report
    if not t.claimed:
        return f"{head}: not claimed certified (not checked)"
    if t.file is None:
        return f"{head}: claimed certified, not re-checked before the refutation"
    stem_note = "" if Path(t.file.path).stem == t.id else " (its id is not the file's name)"
    ignored = (f" ({t.ignored_velocities} recorded velocities in the file ignored: accepted by "
               "--allow-finite-difference)") if t.ignored_velocities else ""
    scene = scenes.get(t.scene)
    return (f"{head}: {_file_line(t.file)}{stem_note}; arrays sha256 {t.arrays_sha256}; velocities "
            f"{t.velocities}{ignored}; scene {t.scene}" + (f" ({scene.file.path})" if scene else "") +
            f"; {t.leaves} leaves re-checked")


def report_lines(report: VerifyReport) -> list[str]:
    """The report for people: the verdict line (VERIFIED; for a refutation, a heading: the
    refutation itself is the caller's line), then what was checked and assumed."""
    name = report.certificate
    if report.refuted is not None:
        out = [f"{name}: established before the refutation:"]
    elif report.checked == 0:
        out = [f"{name}: VERIFIED: none of its {report.trajectories} trajectories is claimed certified "
               "(nothing to re-check)"]
    else:
        out = [f"{name}: VERIFIED: {report.checked} of {report.trajectories} trajectories claimed certified, "
               f"{report.leaves} leaves re-checked with the NumPy float64 reference (smallest clearance above guard "
               f"{report.min_excess_m * 1000:.3f} mm, stored clearances within {report.max_clearance_diff_m:.2g} m)"]
    if report.parameters is not None:
        out += _parameter_lines(report.parameters)
    if report.robot is not None:
        out += _robot_lines(report.robot)
    for s in report.scene_files:
        boxes = f"{len(s.boxes)} obstacles" if s.boxes else "0 obstacles: the claim says nothing about obstacles"
        out.append(f"  scene {s.index}: {_file_line(s.file)}; arrays sha256 {s.arrays_sha256}; {boxes}")
        out += [f"    {a}" for a in s.assumes]
    scenes = {s.index: s for s in report.scene_files}
    out += [_trajectory_line(t, scenes) for t in report.trajectory_files]
    out.append("  pins: " + (", ".join(report.pins) + (" (held)" if report.refuted is None else "")
                             if report.pins else "none"))
    # ids, the method, names and paths come from the files: a newline there would print a line of
    # the certificate's choosing (a pin "held", a file "given by the caller")
    return [one_line(line) for line in out]


def _jsonable(x):
    if isinstance(x, float):
        return x if math.isfinite(x) else None
    if isinstance(x, dict):
        return {k: _jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_jsonable(v) for v in x]
    return x


def report_json(report: VerifyReport) -> dict:
    """The report for machines (``larc verify --json``): every field of :class:`VerifyReport`,
    plus ``verdict`` (``verified`` / ``refuted``) and ``exit_status`` (0 / 1); inf is null."""
    doc = _jsonable(dataclasses.asdict(report))
    verdict = "verified" if report.refuted is None else "refuted"
    return {"verdict": verdict, "exit_status": 0 if report.refuted is None else 1, **doc}


def input_error_json(certificate: str, error: str) -> dict:
    """``larc verify --json`` for bad input (exit status 2)."""
    return {"verdict": "bad input", "exit_status": 2, "certificate": certificate, "error": error}
