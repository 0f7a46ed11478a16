"""The text-option parsers of larc_jax.option_values (--hold, --joints, --package-dir,
--capsules-per-link): good values, and every bad item refused with the option and the item named."""

from __future__ import annotations

import pytest

import larc_jax as lj
from larc_jax import LarcInputError
from larc_jax.option_values import parse_capsules_per_link, parse_hold, parse_joints, parse_package_dirs


def test_good_values():
    assert parse_hold(["joint7=0", "joint8=-0.01", "j=1e-3"]) == {"joint7": 0.0, "joint8": -0.01, "j": 0.001}
    assert parse_hold("joint7=0.02") == {"joint7": 0.02}  # one string is one item
    assert parse_hold(None) == {} and parse_hold([]) == {}
    assert parse_joints("joint1, joint2 ,joint7") == ["joint1", "joint2", "joint7"]
    assert parse_joints(None) is None and parse_joints("") is None
    assert parse_package_dirs(["piper_description=/opt/piper", "b=rel/a=b"]) == {
        "piper_description": "/opt/piper", "b": "rel/a=b"}  # the path may hold '='
    assert parse_capsules_per_link(["link6=2", "link1=1"]) == {"link6": 2, "link1": 1}
    # the public API re-exports the three the CLI and the robot loaders share
    assert (lj.parse_hold, lj.parse_joints, lj.parse_package_dirs) == (parse_hold, parse_joints, parse_package_dirs)


@pytest.mark.parametrize("parse, items, message", [
    (parse_hold, ["joint7"], "--hold 'joint7': expected JOINT=VALUE"),
    (parse_hold, ["joint7="], "--hold 'joint7=': expected JOINT=VALUE"),
    (parse_hold, ["=0"], "--hold '=0': expected JOINT=VALUE"),
    (parse_hold, ["joint7=open"], "--hold 'joint7=open': expected JOINT=VALUE with a finite number"),
    (parse_hold, ["joint7=nan"], "--hold 'joint7=nan': expected JOINT=VALUE with a finite number"),
    (parse_hold, ["joint7=inf"], "--hold 'joint7=inf'"),
    (parse_hold, ["joint7=0", "joint7=-0.01"], "--hold joint7 is given twice"),
    (parse_hold, [7], "--hold 7: expected a string JOINT=VALUE"),
    (parse_joints, "joint1,,joint3", "--joints 'joint1,,joint3': expected comma-separated joint names"),
    (parse_joints, "joint1, ", "--joints 'joint1, '"),
    (parse_joints, ["joint1"], "--joints ['joint1']: expected comma-separated joint names"),
    (parse_package_dirs, ["piper_description"], "--package-dir 'piper_description': expected NAME=PATH"),
    (parse_package_dirs, ["=/opt"], "--package-dir '=/opt': expected NAME=PATH"),
    (parse_package_dirs, ["a=/x", "a=/y"], "--package-dir a is given twice"),
    (parse_capsules_per_link, ["link6=3"], "--capsules-per-link 'link6=3': expected LINK=1 or LINK=2"),
    (parse_capsules_per_link, ["link6=\u00b2"], "--capsules-per-link 'link6=\u00b2'"),  # isdigit, not int
    (parse_capsules_per_link, ["link6"], "--capsules-per-link 'link6': expected LINK=1 or LINK=2"),
    (parse_capsules_per_link, ["link6=1", "link6=2"], "--capsules-per-link link6 is given twice"),
])
def test_bad_items_name_the_option_and_the_item(parse, items, message):
    with pytest.raises(LarcInputError) as err:
        parse(items)
    assert str(err.value).startswith(message) and "\n" not in str(err.value)


def test_python_callers_name_their_own_option():
    with pytest.raises(LarcInputError, match=r"^hold 'joint7': expected JOINT=VALUE"):
        parse_hold(["joint7"], option="hold")
