"""The node's parameters as data: the shipped file, the front-end mapping, parameters files read offline."""

from __future__ import annotations

import argparse

import pytest

from nmnet_ros.core.pipeline import DEFAULT_CONFIG as FRONTEND_DEFAULTS
from nmnet_ros.interface.params import PARAMS, ParamsFileError, check_value, frontend_config, read_params_file
from nmnet_ros.tools.options import replay as add_arguments
from nmnet_ros.tools.replay import given_options, live_node_args, node_params

from .conftest import ROOT

DEFAULTS = {name: default for name, (default, _, _) in PARAMS.items()}


def test_the_node_defaults_are_the_front_end_defaults():
    """A replay without a parameters file runs what it ran before it read them: the front end's own defaults."""
    cfg = frontend_config(DEFAULTS)
    assert cfg == {k: FRONTEND_DEFAULTS[k] for k in cfg}


def test_the_shipped_parameters_file_reads_as_the_defaults():
    warnings = []
    assert read_params_file(ROOT / "config" / "nmnet.yaml", warn=warnings.append) == DEFAULTS and warnings == []


def test_sections_for_the_node_apply_in_file_order_and_others_are_ignored(tmp_path):
    f = tmp_path / "p.yaml"
    f.write_text("/**:\n  ros__parameters:\n    max_keypoints: 500\n    use_sim_time: true\n    max_keypoint: 9\n"
                 "/robot/nmnet_node:\n  ros__parameters:\n    max_keypoints: 700\n    pose_estimator: classic\n"
                 "other_node:\n  ros__parameters:\n    k: 3\n")
    warnings = []
    got = read_params_file(f, warn=warnings.append)
    assert got == {**DEFAULTS, "max_keypoints": 700, "pose_estimator": "classic"}
    assert warnings == [f"{f}: 'max_keypoint' is not an nmnet_node parameter: ignored; did you mean 'max_keypoints'? "
                        "(the list: nmnet_node --help)"]  # as the node says it
    assert frontend_config(got)["pose_estimator"] == "classic"
    # the forms the node takes in a namespace: nested, and a wildcard for the node's name (read as rcl reads them)
    for text in ("front:\n  nmnet_node:\n    ros__parameters:\n      k: 5\n", "/front/*:\n  ros__parameters:\n    k: 5\n"):
        f.write_text(text)
        assert read_params_file(f)["k"] == 5, text


@pytest.mark.parametrize(("text", "match"), [
    (None, "cannot read the parameters file"),
    ("a: [1, 2\nb: 3\n", r"not valid YAML \(line 2, column 2: expected ',' or '\]', but got ':'\)$"),
    ("- 1\n- 2\n", "not a ROS 2 parameters file"),
    ("other_node:\n  ros__parameters:\n    k: 3\n", r"no ros__parameters for /\*\* or nmnet_node \(found: other_node\)"),
    ("/**:\n  ros__parameters:\n    max_keypoints: lots\n", "max_keypoints: 'lots' is a string, the setting an integer"),
    ("/**:\n  ros__parameters:\n    score_threshold: 1\n", r"score_threshold: 1 is an integer, the setting a float \(write 1.0\)"),
    ("/**:\n  ros__parameters:\n    rectified: 1\n", "rectified: 1 is an integer, the setting a bool"),
    ("/**:\n  ros__parameters:\n    max_keypoints: 50\n", "max_keypoints: 50 is out of range 100 .. 8000"),
    ("/**:\n  ros__parameters:\n    pose_estimator: fancy\n", "pose_estimator: 'fancy' is not one of"),
    ("/front/nmnet_node:\n  ros__parameters:\n    k: 6\nrear/nmnet_node:\n  ros__parameters:\n    k: 4\n",
     r"sections for several nodes \(/front/nmnet_node, /rear/nmnet_node\); a replay is one camera's"),
], ids=["missing", "yaml", "not-a-mapping", "no-section", "type", "int-for-float", "int-for-bool", "range", "choice",
        "two-cameras"])
def test_a_bad_parameters_file_names_the_file_and_the_problem(tmp_path, text, match):
    f = tmp_path / "p.yaml"
    if text is not None:
        f.write_text(text)
    with pytest.raises(ParamsFileError, match=f"^{f}: {match}"):
        read_params_file(f)


def test_every_default_passes_its_own_check():
    assert all(check_value(name, default) is None for name, default in DEFAULTS.items())


def test_a_live_replay_hands_the_node_the_settings_the_replay_runs_with(tmp_path):
    """The node was given the --params-file itself, whose /robot/nmnet_node section rcl applies to a node in /robot
    only: the live node ran the defaults while the summary said the file's values."""
    p = argparse.ArgumentParser()
    add_arguments(p)
    mine = tmp_path / "mine.yaml"
    mine.write_text("/robot/nmnet_node:\n  ros__parameters:\n    max_keypoints: 300\n    detector: sift\n"
                    "    weights: '/my weights/a: b.pt'\n    static_flow_px: 1.0\n")  # the last one: its default
    args = p.parse_args(["bag", "--out", "o.mcap", "--params-file", str(mine), "--max-keypoints", "500", "--rectified"])
    assert live_node_args(node_params(args)) == ["-p", 'weights:="/my weights/a: b.pt"', "-p", 'detector:="sift"',
                                                 "-p", "max_keypoints:=500", "-p", "rectified:=true"]
    assert live_node_args(node_params(p.parse_args(["bag", "--out", "o.mcap"]))) == []


def test_replay_names_a_node_setting_as_the_node_does():
    """The node's pose_estimator was only reachable as --selector with eval's names, nmnet_precision as --precision."""
    p = argparse.ArgumentParser()
    add_arguments(p)
    args = p.parse_args(["bag", "--out", "o.mcap", "--pose-estimator", "classic", "--nmnet-precision", "float32"])
    assert given_options(args) == {"nmnet_precision": "float32", "pose_estimator": "classic"}
    assert p.parse_args(["bag", "--out", "o.mcap", "--precision", "float32"]).nmnet_precision == "float32"  # former name
    args = p.parse_args(["bag", "--out", "o.mcap", "--pose-estimator", "ratio+magsac"])  # eval's name for classic
    assert given_options(args) == {"pose_estimator": "classic"}  # the node's name for it
    with pytest.raises(SystemExit):
        p.parse_args(["bag", "--out", "o.mcap", "--pose-estimator", "fancy"])


def test_which_parameters_file_sections_reach_a_node_as_rcl_matches_them():
    """Checked against rcl on 2026-12-04 (rclpy 9.1.2, a node /front/nmnet_node and /nmnet_node): the same verdicts."""
    from nmnet_ros.interface.params import file_sections, not_parameters, section_applies

    for name, front, root in (("/**", True, True), ("**", True, True), ("nmnet_node", False, True), ("/nmnet_node", False, True),
                              ("front/nmnet_node", True, False), ("/front/*", True, False), ("/**/nmnet_node", True, True),
                              ("/*/nmnet_node", True, False), ("/nmnet", False, False), ("/camera_driver", False, False)):
        assert (section_applies(name, "/front/nmnet_node"), section_applies(name, "/nmnet_node")) == (front, root), name
    doc = {"front": {"nmnet_node": {"ros__parameters": {"k": 4}}}, "/**": {"ros__parameters": {"k": 8}}, "x": 3}
    assert file_sections(doc) == [("/front/nmnet_node", {"k": 4}), ("/**", {"k": 8})] and file_sections([1]) == []
    said = not_parameters(["max_keypoint", "k", "use_sim_time", "qos_overrides./image.subscription.depth", "zzz"])
    assert said == ["'max_keypoint' is not an nmnet_node parameter: ignored; did you mean 'max_keypoints'? "
                    "(the list: nmnet_node --help)", "'zzz' is not an nmnet_node parameter: ignored (the list: nmnet_node --help)"]


def test_the_shipped_parameters_file_and_the_docs_table_are_made_from_the_settings():
    """config/nmnet.yaml and docs/parameters.md are generated from core/settings.py: a setting added, renamed or
    given another default there and not regenerated fails here (python -m nmnet_ros.interface.params yaml|markdown)."""
    from nmnet_ros.interface.params import params_yaml, settings_table

    assert (ROOT / "config" / "nmnet.yaml").read_text() == params_yaml()
    assert (ROOT / "docs" / "parameters.md").read_text().endswith("<!-- settings table: generated -->\n" + settings_table())


def test_a_setting_has_one_name_on_the_node_the_front_end_and_every_tool():
    """The node's pose_estimator was the tools' --selector, nmnet_precision their --precision, pose_threshold_px eval's
    --threshold-px, and the Frontend's keys were others again (selector, precision, threshold_px, mutual/ratio)."""
    from nmnet_ros.core.bf16 import PRECISIONS
    from nmnet_ros.core.detectors import DETECTORS
    from nmnet_ros.core.pipeline import DEFAULT_CONFIG
    from nmnet_ros.core.settings import BY_NAME, DETECTOR_NAMES, SETTINGS, for_tool
    from nmnet_ros.tools.cli import SUBCOMMANDS

    assert set(DETECTOR_NAMES) == set(DETECTORS) and PRECISIONS == BY_NAME["nmnet_precision"].choices
    assert set(DEFAULT_CONFIG) == {s.name for s in SETTINGS if s.frontend}
    assert set(PARAMS) == {s.name for s in SETTINGS if s.node}
    for command, (_, add_options, _) in SUBCOMMANDS.items():
        p = argparse.ArgumentParser()
        add_options(p)
        by_dest = {a.dest: a for a in p._actions}
        for s in for_tool(command):
            assert by_dest[s.name].option_strings[0] == s.option, (command, s.name)
        for dest, action in by_dest.items():  # no option sets a setting under another name
            names = {o.lstrip("-").replace("-", "_") for o in action.option_strings}
            assert not (names & set(BY_NAME)) or dest in BY_NAME, (command, action.option_strings)


def test_a_setting_the_pose_estimator_does_not_read_is_a_warning_not_a_silent_change():
    """Under the default (PoseLib PROSAC) the MAGSAC++ polish, the network's cut and the classic fallback are not
    read: a changed value is a warning naming the setting and the estimators that read it; a value left at its
    default, or read by the estimator chosen, is not."""
    import warnings

    from nmnet_ros.core.pipeline import Frontend
    from nmnet_ros.core.settings import FRONTEND_DEFAULTS, METHODS, SETTINGS, inert

    assert all(set(s.methods) <= set(METHODS) for s in SETTINGS)
    changed = {"pose_refine_iterations": 10, "score_threshold": 0.9, "fallback_min_inliers": 0}
    lines = inert({**FRONTEND_DEFAULTS, **changed})
    assert len(lines) == 3 and lines[1] == ("pose_refine_iterations 10 has no effect with pose_estimator 'prosac': "
                                            "only ratio_magsac, magsac, classic read it")
    assert inert(FRONTEND_DEFAULTS) == [] and inert({**FRONTEND_DEFAULTS, "pose_estimator": "ratio_magsac", **changed}) == []
    assert inert({**FRONTEND_DEFAULTS, "pose_estimator": "ratio+prosac", "pose_refine_iterations": 0}) == [
        "pose_refine_iterations 0 has no effect with pose_estimator 'ratio+prosac': only ratio_magsac, magsac, classic "
        "read it"]
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        Frontend(None, {"pose_refine_iterations": 10})
    assert [str(w.message) for w in caught] == [lines[1]]
