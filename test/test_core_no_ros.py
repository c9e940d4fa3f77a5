"""Without ROS: the algorithmic core imports no ROS module, the offline tools run, the ROS shells say what is missing."""

import json
import subprocess
import sys

import pytest

from .conftest import ROOT

CORE = ["core.features", "core.matching", "core.neighbors", "core.geometry", "core.planes", "io.datasets", "io.asl",
        "io.kitti", "io.tum", "core.model", "io.pairs", "core.metrics", "io.cache", "tools.train",
        "tools.neighbor_study", "interface.imgconv", "interface.caminfo", "interface.posemsg", "io.outputs"]
# nmnet replay (offline), eval, make-bag, bench
OFFLINE_TOOLS = ["tools.evaluate", "tools.replay", "tools.make_bag", "tools.bench", "tools.cli", "interface.params"]


@pytest.mark.slow
@pytest.mark.parametrize("modules", [CORE, OFFLINE_TOOLS], ids=["core", "offline-tools"])
def test_imports_no_ros(modules):
    code = (
        "import sys\n"
        + "".join(f"import nmnet_ros.{m}\n" for m in modules)
        + "from nmnet_ros.ros.entry import ROS_PACKAGES\n"
        "bad = sorted(m for m in sys.modules if m.split('.')[0] in ROS_PACKAGES | {'nav_msgs'})\n"
        "print(','.join(bad))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.strip()
    assert out == "", f"{modules} pulled in ROS modules: {out}"


def test_cli_lists_subcommands():
    out = subprocess.run([sys.executable, "-m", "nmnet_ros.tools.cli", "--help"], capture_output=True, text=True, check=True).stdout
    for sub in ("demo", "train", "eval", "neighbors", "bench"):
        assert sub in out


def test_cli_without_a_command_fails_naming_the_commands():
    """Bare `nmnet` is a usage error (exit 2, as argparse's), not success: a script would read it as done."""
    run = subprocess.run([sys.executable, "-m", "nmnet_ros.tools.cli"], capture_output=True, text=True)
    assert run.returncode == 2 and run.stdout == ""
    assert "error: name a command: " in run.stderr and "replay" in run.stderr.splitlines()[-1]


@pytest.mark.parametrize("argv, option, why", [
    (["eval", "d", "--stride", "0"], "--stride", "'0': expected a whole number >= 1"),  # was a ZeroDivisionError
    (["eval", "d", "--max-pairs", "-3"], "--max-pairs", "'-3': expected a whole number >= 1"),  # was numpy's message
    (["eval", "d", "--gaps", "-1"], "--gaps", "'-1': expected frame gaps >= 1"),  # was "invalid literal for int()"
    (["eval", "d", "--gaps", "3-1"], "--gaps", "'3-1': expected frame gaps >= 1"),  # was "no pairs ... to evaluate"
    (["train", "--train", "d", "--val", "d", "--out", "o", "--epochs", "0"], "--epochs", "'0': expected a whole number >= 1"),
    (["train", "--train", "d", "--val", "d", "--out", "o", "--seed", "x"], "--seed", "'x': expected a whole number >= 0"),
    (["neighbors", "d", "--k", "0"], "--k", "k: 0 is out of range 2 .. 16"),
    (["bench", "--repeat", "0"], "--repeat", "'0': expected a whole number >= 1"),
    (["label", "r", "o", "--max-frames", "5"], "--max-frames", "'5': expected a whole number >= 10"),  # never enough
    (["bench", "--sizes", "abc"], "--sizes", "'abc': expected correspondence counts from 1 to 8000"),  # was "invalid literal"
    (["bench", "--sizes", "1000,0"], "--sizes", "'1000,0': expected correspondence counts from 1 to 8000"),  # was a row of 0s
    (["bench", "--sizes", "100000"], "--sizes", "'100000': expected correspondence counts from 1 to 8000 (the node's "
                                                "largest max_keypoints)"),  # the loop baseline ran for hours
    # an output file ending in '/' meant a folder: it became a file of the folder's name
    (["replay", "b.mcap", "--out", "o.mcap", "--json", "res/"], "--json", "'res/' ends in '/', a folder"),
    (["eval", "d", "--json", "res/"], "--json", "'res/' ends in '/', a folder"),
    (["eval", "d", "--plot", "res/"], "--plot", "'res/' ends in '/', a folder"),
    (["bench", "--json", "res/"], "--json", "'res/' ends in '/', a folder"),
    (["neighbors", "d", "--json", "res/"], "--json", "'res/' ends in '/', a folder"),
])
def test_a_count_or_gap_out_of_range_is_refused_naming_the_option(argv, option, why, capsys):
    """The tools' counts and frame gaps are checked as they are parsed (exit 2, argparse's line naming the option)
    instead of failing later with Python's or numpy's message, or running on nothing."""
    from nmnet_ros.tools.cli import main

    with pytest.raises(SystemExit) as stop:
        main(argv)
    assert stop.value.code == 2
    assert f"argument {option}: {why}" in capsys.readouterr().err


def test_a_replay_out_ending_in_a_slash_is_refused_as_a_file_name_that_is_a_folder(capsys):
    """One recording's --out is a file: 'results/' meant a folder and became a file of the folder's name (with
    several recordings --out is the run's folder, so this is checked once the recordings are counted)."""
    from nmnet_ros.tools.cli import main

    assert main(["replay", "b.mcap", "--out", "results/"]) == 2
    assert "--out 'results/' ends in '/', a folder: give a file name in it" in capsys.readouterr().err


def test_the_number_types_take_what_they_should_and_nothing_else():
    """cli.gaps' two forms; cli.bounded's bound (inclusive, or strict as --rate's) and its refusal of NaN and inf."""
    import argparse

    from nmnet_ros.tools.options import bounded, gaps, whole

    assert gaps("1-3") == (1, 2, 3) and gaps("1,5") == (1, 5) and gaps("4") == (4,)
    assert whole(0)("0") == 0 and bounded(float, 0.0, "seconds")("0") == 0.0
    rate = bounded(float, 0.0, "a speed factor > 0", strict=True)
    assert rate("0.5") == 0.5
    for bad in ("0", "-1", "nan", "inf", "fast"):
        with pytest.raises(argparse.ArgumentTypeError, match=f"'{bad}': expected a speed factor > 0"):
            rate(bad)


# what a Python without rclpy and the message packages sees (arm64 with no ROS 2 sourced): their imports fail
def _without_ros(code: str, cwd, blocked: str = "ROS_PACKAGES") -> subprocess.CompletedProcess:
    """Run ``code`` in a Python where the ``blocked`` packages (an expression; default: all of ROS) fail to import."""
    block = f"import sys\nfrom nmnet_ros.ros.entry import ROS_PACKAGES\nfor m in {blocked}: sys.modules[m] = None\n"
    return subprocess.run([sys.executable, "-c", block + code], capture_output=True, text=True, cwd=cwd, timeout=300)


def test_without_ros_the_node_and_live_replay_say_what_is_missing(tmp_path):
    """nmnet_node (the console script or `python -m nmnet_ros.node`) and `nmnet replay --live` stop with one line
    naming the package and the two ways to get it (exit code 2, no traceback); the live replay stops before it makes
    its output file."""
    from nmnet_ros.tools.options import SAMPLE_BAG

    node = _without_ros("from nmnet_ros.ros.entry import node_main\nsys.exit(node_main(['nmnet_node']))", tmp_path)
    module = _without_ros("import runpy\nsys.argv = ['node.py']\nrunpy.run_module('nmnet_ros.node', run_name='__main__')",
                          tmp_path)  # what `python -m nmnet_ros.node` runs
    live = _without_ros(f"from nmnet_ros.tools.cli import main\nsys.exit(main(['replay', {str(SAMPLE_BAG)!r}, '--live', "
                        "'--out', 'live.mcap']))", tmp_path)
    for done, prog in ((node, "nmnet_node"), (module, "nmnet_node"), (live, "nmnet replay")):
        assert done.returncode == 2, done.stderr
        assert done.stderr.startswith(f"{prog}: error: the ROS 2 Python package 'rclpy' is missing"), done.stderr
        assert "source /opt/ros/kilted/setup.bash" in done.stderr and "Traceback" not in done.stderr
    assert not (tmp_path / "live.mcap").exists()


def test_live_replay_names_a_missing_message_package_the_node_needs(tmp_path):
    """A ROS install with rclpy but without std_srvs (the node's ~/reset): `nmnet replay --live` names the package
    before it starts the node or makes its output file (the node would exit before subscribing)."""
    from nmnet_ros.tools.options import SAMPLE_BAG

    live = _without_ros(f"from nmnet_ros.tools.cli import main\nsys.exit(main(['replay', {str(SAMPLE_BAG)!r}, '--live', "
                        "'--out', 'live.mcap']))", tmp_path, blocked="['std_srvs']")
    assert live.returncode == 2, live.stderr
    assert live.stderr.startswith("nmnet replay: error: the ROS 2 Python package 'std_srvs' is missing"), live.stderr
    assert not (tmp_path / "live.mcap").exists()


def test_live_mode_checks_every_ros_package_the_player_and_node_import():
    """require_ros's list covers the ROS packages live.py and node.py import (it would miss a new one otherwise)."""
    import ast

    from nmnet_ros.ros.entry import ROS_PACKAGES
    from nmnet_ros.tools.live import LIVE_ROS_PACKAGES

    imported = set()
    for module in ("tools/live", "ros/node"):
        tree = ast.parse((ROOT / "nmnet_ros" / f"{module}.py").read_text())
        for n in ast.walk(tree):
            if isinstance(n, ast.Import):
                imported |= {a.name.split(".")[0] for a in n.names}
            elif isinstance(n, ast.ImportFrom) and n.level == 0 and n.module:
                imported.add(n.module.split(".")[0])
    assert {"rclpy", "std_srvs", "sensor_msgs"} <= imported  # the walk sees the imports
    assert imported & ROS_PACKAGES <= set(LIVE_ROS_PACKAGES), imported & ROS_PACKAGES


@pytest.mark.slow
def test_node_help_lists_topics_service_and_every_parameter_without_ros(tmp_path):
    """`nmnet_node --help` prints the usage, topics, the reset service and every parameter with its default and
    range (from params.PARAMS, so it cannot drift), without starting the node, so also without ROS; a -h among the
    ROS arguments is a parameter value, not a request for help."""
    from nmnet_ros.interface.params import PARAMS, STARTUP_ONLY

    done = _without_ros("from nmnet_ros.ros.entry import node_main\nsys.exit(node_main(['nmnet_node', '--help']))", tmp_path)
    assert done.returncode == 0 and done.stderr == "", done.stderr
    out = done.stdout
    assert out.startswith("usage: nmnet_node") and "~/reset (std_srvs/srv/Trigger)" in out and "~/relative_pose" in out
    for name, (default, _, rng) in PARAMS.items():
        line = next((x for x in out.splitlines() if x.startswith(f"  {name} ")), None)
        assert line is not None, name
        assert line.startswith(f"  {name} *" if name in STARTUP_ONLY else f"  {name} ("), line
        assert json.dumps(default) in line and (rng is None or str(rng[-1]) in line), line
    ros_value = _without_ros("from nmnet_ros.ros.entry import node_main\n"
                             "sys.exit(node_main(['nmnet_node', '--ros-args', '-p', 'weights:=-h']))", tmp_path)
    assert ros_value.returncode == 2 and "'rclpy' is missing" in ros_value.stderr  # went on to start the node


def test_version_is_the_packages_and_stray_node_arguments_are_refused(tmp_path):
    """`nmnet --version` and `nmnet_node --version` print the installed version, which setup.py and package.xml
    both carry; an argument before --ros-args (rclpy would ignore it and start with the defaults) is refused."""
    import re

    xml = re.search(r"<version>(.+)</version>", (ROOT / "package.xml").read_text()).group(1)
    assert f'version="{xml}"' in (ROOT / "setup.py").read_text()
    tool = subprocess.run([sys.executable, "-m", "nmnet_ros.tools.cli", "--version"], capture_output=True, text=True)
    node = _without_ros("from nmnet_ros.ros.entry import node_main\nsys.exit(node_main(['nmnet_node', '--version']))", tmp_path)
    for done in (tool, node):
        assert done.returncode == 0 and done.stdout == f"nmnet_ros {xml}\n", done.stdout + done.stderr
    stray = _without_ros("from nmnet_ros.ros.entry import node_main\n"
                         "sys.exit(node_main(['nmnet_node', '-p', 'max_keypoints:=1000']))", tmp_path)
    assert stray.returncode == 2 and stray.stderr.startswith(
        "nmnet_node: error: unrecognized arguments: -p max_keypoints:=1000; node settings go after --ros-args"), stray.stderr


def test_demo_runs_its_offline_part_without_ros(tmp_path):
    """The offline tools need no ROS: `nmnet demo` skips the live part with the note and replays the sample
    bag offline, next to the SIFT baseline; its output holds the node's topics."""
    from mcap.reader import make_reader

    done = _without_ros("from nmnet_ros.tools.cli import main\nsys.exit(main(['demo', '--out-dir', 'demo']))", tmp_path)
    assert done.returncode == 0, done.stderr[-2000:]
    assert "1/2 live: skipped: the ROS 2 Python package 'rclpy' is missing" in done.stdout
    summary = json.loads((tmp_path / "demo" / "summary.json").read_text())
    assert summary["processed"] == summary["frames"] == 40 and summary["baseline"]["processed"] == 40
    with open(tmp_path / "demo" / "nmnet_output.mcap", "rb") as f:
        topics = {channel.topic for _, channel, _ in make_reader(f).iter_messages()}
    assert topics == {"/nmnet_node/matches", "/nmnet_node/relative_pose"}
    assert not (tmp_path / "demo" / "nmnet_live.mcap").exists()


def test_ros_wheels_are_required_only_where_pypi_has_them():
    """requirements.txt: the ros-* wheels (PyPI has them for x86_64 Linux only) carry a marker for that
    platform, and so do the packages only they bring in, so `pip install -r requirements.txt` also works on arm64 beside a
    ROS 2 install; the rest apply everywhere."""
    from pathlib import Path

    from packaging.requirements import Requirement

    lines = [line for line in (Path(__file__).resolve().parents[1] / "requirements.txt").read_text().splitlines()
             if line.strip() and not line.startswith("#")]
    reqs = [Requirement(line) for line in lines]
    linux = {"sys_platform": "linux", "platform_system": "Linux"}
    for r in reqs:
        assert r.marker is not None or not r.name.startswith("ros-"), r
        if r.marker is not None:  # a ros-* wheel, or a package that only they need (empy, lark-parser)
            assert r.marker.evaluate({**linux, "platform_machine": "x86_64"}), r
            assert not r.marker.evaluate({**linux, "platform_machine": "aarch64"}), r
            assert not r.marker.evaluate({"sys_platform": "darwin", "platform_system": "Darwin", "platform_machine": "arm64"}), r
        assert len(r.specifier) == 1 and next(iter(r.specifier)).operator == "==", f"{r}: not pinned exactly"
    assert {r.name for r in reqs} >= {"ros-rclpy", "torch", "rosbags", "mcap"}


@pytest.mark.parametrize("argv, example", [(["bench"], "bench.json"), (["neighbors", "d"], "neighbors.json"),
                                           (["eval", "d"], "eval.json")])
def test_an_output_file_that_cannot_be_written_is_refused_before_the_work(argv, example, tmp_path, capsys):
    """A folder given as --json, or a file in the way of its folder: said at once, not after minutes of work (which
    the result was lost with); a folder not there yet is made."""
    from nmnet_ros.io.outputs import output_file
    from nmnet_ros.tools.cli import main

    afile = tmp_path / "afile"
    afile.write_text("")
    for path, said in ((tmp_path, f"--json {tmp_path} is a folder: give a file name, e.g. {tmp_path / example}"),
                       (afile / "sub" / "r.json", f"--json {afile / 'sub' / 'r.json'}: {afile} is a file, not a folder")):
        assert main([*argv, "--json", str(path)]) == 2
        assert said in capsys.readouterr().err
    output_file(tmp_path / "new" / "deeper" / "r.json", "--json", example)
    assert (tmp_path / "new" / "deeper").is_dir()


def test_a_tools_options_may_come_between_its_positionals(capsys):
    """`nmnet label imgs --camera c.yaml out` said "nmnet: error: unrecognized arguments: out" under the usage of all
    tools: argparse took the subcommand's positionals in one pass, before the option."""
    from pathlib import Path

    from nmnet_ros.tools.cli import parse_args

    args = parse_args(["label", "a", "--camera", "c.yaml", "b"])
    assert (args.recordings, args.camera, args.command) == (["a", "b"], Path("c.yaml"), "label")
    assert parse_args(["eval", "a", "--gaps", "1-3", "b", "--seeds", "2"]).seqs == ["a", "b"]
    assert parse_args(["make-bag", "seq", "--compressed", "o.mcap"]).out_positional == Path("o.mcap")
    with pytest.raises(SystemExit):
        parse_args(["replay", "a.mcap", "--camera", "c.yaml"])
    assert "nmnet replay: error: the following arguments are required: --out" in capsys.readouterr().err


@pytest.mark.parametrize("methods, said", [("ratio,magsak", "unknown method(s) ['magsak']; choose from nmnet, "),
                                           ("ratio,classic", "unknown method(s) ['classic'] (classic is the node's "
                                            "pose_estimator; here it is ratio+magsac); choose from nmnet, "),
                                           # one name, two meanings: the node's magsac fits NM-Net's selection
                                           ("magsac", "unknown method(s) ['magsac'] (magsac is the node's pose_estimator; "
                                            "here it is nmnet+magsac) (MAGSAC++/RANSAC on all the matches, formerly "
                                            "magsac, is now nn+magsac); choose from nmnet, "),
                                           ("ransac", "unknown method(s) ['ransac'] (MAGSAC++/RANSAC on all the matches, "
                                            "formerly ransac, is now nn+ransac); choose"),
                                           ("", "--methods names none; choose from nmnet, "),
                                           (" , ", "--methods names none; choose from nmnet, ")])
def test_eval_methods_unknown_or_none_are_refused_before_any_work(methods, said, capsys):
    """An empty --methods evaluated nothing: an empty table and plot, exit 0."""
    from nmnet_ros.tools.cli import main

    assert main(["eval", "no_such_folder", "--methods", methods]) == 2
    assert f"nmnet eval: error: {said}" in capsys.readouterr().err


def test_a_demo_out_dir_that_is_a_file_is_named(tmp_path, capsys):
    """`nmnet demo --out-dir` a file said '[Errno 17] File exists', through a file '[Errno 20] Not a directory'."""
    from nmnet_ros.tools.cli import main

    afile = tmp_path / "afile"
    afile.write_text("a user's file")
    for out, said in ((afile, f"--out {afile} is a file: give a folder for the demo's outputs"),
                      (afile / "sub", f"--out {afile / 'sub'}: {afile} is a file, not a folder")):
        for flag in ("--out", "--out-dir"):  # --out as train's; --out-dir, its former name, still works
            assert main(["demo", flag, str(out)]) == 2
            assert f"nmnet demo: error: {said}" in capsys.readouterr().err
    assert afile.read_text() == "a user's file"


def test_a_replay_into_an_existing_folder_or_a_file_without_mcap_suffix_is_refused_naming_one(tmp_path, capsys):
    """`--out results` where results/ exists (rosbag2's -o takes a folder) said only 'Is a directory'; `--out out`
    wrote an MCAP file that neither rosbags nor nmnet replay could then open, lacking the suffix."""
    from nmnet_ros.tools.cli import main

    assert main(["replay", str(ROOT / "nmnet_ros" / "sample" / "kitti07_120-159"), "--out", str(tmp_path)]) == 2
    assert f"--out {tmp_path} is a folder: give a file name, e.g. {tmp_path / 'nmnet.mcap'}" in capsys.readouterr().err
    assert list(tmp_path.iterdir()) == []
    for name in ("out", "out.db3"):  # an MCAP file no reader would open by its name (rosbags: "Unrecognized storage")
        assert main(["replay", str(ROOT / "nmnet_ros" / "sample" / "kitti07_120-159"), "--out", str(tmp_path / name)]) == 2
        assert f"--out {tmp_path / name}: the output is an MCAP file, which ros2 bag, rosbags and nmnet replay know by " \
               f"its .mcap suffix: give {tmp_path / 'out.mcap'}" in capsys.readouterr().err
    assert list(tmp_path.iterdir()) == []


def test_every_option_of_every_tool_says_what_it_does_and_its_default():
    """Several options had no help text, and no --help showed a default."""
    import argparse

    from nmnet_ros.tools.cli import SUBCOMMANDS
    from nmnet_ros.tools.options import HelpFormatter

    for name, (_, add_options, _) in SUBCOMMANDS.items():
        p = argparse.ArgumentParser(prog=f"nmnet {name}", formatter_class=HelpFormatter)
        add_options(p)
        bare = [a.option_strings or a.dest for a in p._actions if not a.help and not isinstance(a, argparse._HelpAction)]
        assert not bare, (name, bare)
    out = subprocess.run([sys.executable, "-m", "nmnet_ros.tools.cli", "train", "--help"], capture_output=True, text=True,
                         check=True).stdout
    assert "Adam's learning rate (default: 0.001)" in " ".join(out.split())


def test_help_imports_no_heavy_module_and_outputs_are_named_one_way(capsys):
    """Every subcommand's --help took 3-4 s: it imported torch to list the options. The options now come from
    tools/options.py and the settings vocabulary, and a tool's module loads only when it runs. Outputs: --out for a
    tool's main output (make-bag's, once a positional, is still taken there), --json for numbers, --plots for figures."""
    code = ("import sys\nfrom nmnet_ros.tools.cli import build_parser\np = build_parser()\n"
            "for c in ('replay', 'eval', 'train', 'neighbors', 'bench', 'make-bag', 'demo'):\n"
            "    try:\n        p.parse_args([c, '--help'])\n    except SystemExit:\n        pass\n"
            "print(sorted(m for m in ('torch', 'numba', 'rosbags', 'rclpy', 'kornia') if m in sys.modules), "
            "file=sys.stderr)")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert r.stderr.strip().splitlines()[-1] == "[]", r.stderr
    from nmnet_ros.tools.cli import main

    for argv in (["make-bag", "seq"], ["make-bag", "seq", "a", "--out", "b"]):
        assert main(argv) == 2
        assert "name the output once: --out BAG" in capsys.readouterr().err
