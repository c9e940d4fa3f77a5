"""The node's parameters (names, defaults, ranges, what they do) and the front-end config they map to.

ROS-free, so the offline tools read the same parameters files as the node: ``nmnet replay
--params-file config/nmnet.yaml`` replays a bag with the settings the robot runs.
"""

from __future__ import annotations

import difflib
import fnmatch
import json
import re
import textwrap
from collections.abc import Callable, Iterable
from pathlib import Path

import yaml

from ..core.settings import FRONTEND_DEFAULTS, NODE, POSE_ESTIMATORS, SETTINGS, problem

# name: (default, description, range or choices) of every node parameter, from the settings vocabulary
PARAMS: dict[str, tuple] = {s.name: (s.default, s.full_help, s.choices or s.range) for s in NODE}
SELECTORS = POSE_ESTIMATORS  # pose_estimator -> the selector it runs
# Fixed once the node runs (subscriptions, thread pools, the start-up camera); every other parameter
# can be changed with `ros2 param set` and takes effect from the next frame.
STARTUP_ONLY = tuple(s.name for s in NODE if s.startup_only)


def frontend_config(p: dict) -> dict:
    """The front end's config for the node's parameter values (the settings it has, by the same names)."""
    return {name: p[name] for name in FRONTEND_DEFAULTS if name in p}


def pose_sigmas(p: dict) -> tuple[float, float]:
    """(rotation degrees, direction) sigmas of the published covariance at 200 matches, for ``posemsg``."""
    return p["pose_sigma_rotation_deg"], p["pose_sigma_direction"]


def check_choices(p: dict) -> None:
    """ValueError for a string parameter outside its choices (rclpy checks only types and ranges)."""
    for s in NODE:
        if s.choices and (why := problem(s.name, p[s.name])) is not None:
            raise ValueError(f"parameter {why}")


NODE_NAME = "nmnet_node"
ROS_COMMON = ("use_sim_time",)  # parameters every ROS 2 node has: allowed in a file, nothing to do offline
ROS_BUILTIN = ("start_type_description_service",)  # rclpy declares it too (and qos_overrides.*)


class ParamsFileError(ValueError):
    """A parameters file that cannot be read, or holds a value the node would refuse."""


# Why the node would refuse a value for a parameter (None: it takes it), as rclpy and the node check: types strict,
# as rclpy's (a float parameter given an integer is refused: write ``1.0``).
check_value = problem


def _sections(doc: object, path: Path) -> list[dict]:
    """The ``ros__parameters`` mappings of a ROS 2 parameters file that apply to the node in some namespace (a replay
    is one camera's: ``/**``, ``nmnet_node``, ``/front/nmnet_node``, ``/front/*``), in file order."""
    if not isinstance(doc, dict):
        raise ParamsFileError(f"{path}: not a ROS 2 parameters file (a mapping of node names to ros__parameters)")
    found, nodes = [], set()
    for name, params in file_sections(doc):
        last = name.rsplit("/", 1)[-1]
        if last == "**" or fnmatch.fnmatchcase(NODE_NAME, last):
            found.append(params)
            if "*" not in name:
                nodes.add(name)
    if not found:
        raise ParamsFileError(f"{path}: no ros__parameters for /** or {NODE_NAME} (found: {', '.join(map(str, doc)) or 'nothing'})")
    if len(nodes) > 1:  # a robot's file for several cameras: which one's values a replay takes is not for us to guess
        raise ParamsFileError(f"{path}: sections for several nodes ({', '.join(sorted(nodes))}); a replay is one camera's: "
                              "give a file with that camera's section (and /** for what they share)")
    return found


def not_parameters(names: Iterable[str]) -> list[str]:
    """What to say of names given to the node as parameters (``-p``, a parameters file) that it does not have: rclpy
    ignores them without a word, so a misspelt one (``max_keypoint``) left the default in force unseen."""
    said = []
    for name in names:
        if name in PARAMS or name in ROS_COMMON or name in ROS_BUILTIN or name.startswith("qos_overrides."):
            continue
        near = difflib.get_close_matches(name, PARAMS, n=1)
        said.append(f"{name!r} is not an {NODE_NAME} parameter: ignored" + (f"; did you mean {near[0]!r}?" if near else "")
                    + " (the list: nmnet_node --help)")
    return said


def file_sections(doc: object) -> list[tuple[str, dict]]:
    """(node name, ``ros__parameters``) of every section of a ROS 2 parameters file; nested namespaces are joined."""
    found: list[tuple[str, dict]] = []

    def walk(name: str, body: object) -> None:
        if not isinstance(body, dict):
            return
        if isinstance(body.get("ros__parameters"), dict):
            found.append((name, body["ros__parameters"]))
        for key, inner in body.items():
            if key != "ros__parameters":
                walk(f"{name}/{str(key).strip('/')}", inner)

    for key, body in (doc.items() if isinstance(doc, dict) else ()):
        walk("/" + str(key).strip("/"), body)
    return found


def section_applies(name: str, node: str) -> bool:
    """Whether a parameters file's section (``/**``, ``nmnet_node``, ``/front/*``) applies to the node of fully
    qualified name ``node``, as rcl matches them: ``*`` stands for one name, ``**`` for any number."""
    def match(pattern: list[str], names: list[str]) -> bool:
        if not pattern:
            return not names
        if pattern[0] == "**":
            return any(match(pattern[1:], names[i:]) for i in range(len(names) + 1))
        return bool(names) and fnmatch.fnmatchcase(names[0], pattern[0]) and match(pattern[1:], names[1:])

    return match([t for t in name.split("/") if t], [t for t in node.split("/") if t])


def yaml_problem(e: yaml.YAMLError) -> str:
    """A YAML parser's error on one line, where and what (``line 2, column 5: mapping values are not allowed here``):
    PyYAML's own message spans four lines and names "<unicode string>"."""
    mark, what = getattr(e, "problem_mark", None), getattr(e, "problem", None) or str(e).splitlines()[0]
    return f"line {mark.line + 1}, column {mark.column + 1}: {what}" if mark is not None else what


def params_file_misses(path: Path, node: str) -> str | None:
    """What to say when a parameters file given to the node has no section for it (rclpy applies none of it, silently:
    a section keyed ``nmnet`` or another node's name); None when one applies or the file cannot be read (rcl said)."""
    try:
        sections = file_sections(yaml.safe_load(Path(path).read_text()))
    except (OSError, yaml.YAMLError):
        return None
    if any(section_applies(name, node) for name, _ in sections):
        return None
    return (f"{path}: no section applies to {node} (sections: {', '.join(n for n, _ in sections) or 'none'}): none of its "
            f"parameters are in force; key them /** or {node} (config/nmnet.yaml's form)")


def read_params_file(path: Path, warn: Callable[[str], None] = print) -> dict:
    """Every node parameter's value from a ROS 2 parameters file (``config/nmnet.yaml``'s form), defaults for the rest.

    Sections for ``/**`` and for the node (``nmnet_node``, any namespace, only one) apply in file order. A value the
    node would refuse raises :class:`ParamsFileError` naming the file and the parameter; a name the node
    does not have is reported through ``warn`` and ignored, as the node ignores it.
    """
    path = Path(path)
    try:
        doc = yaml.safe_load(path.read_text())
    except OSError as e:
        raise ParamsFileError(f"{path}: cannot read the parameters file ({e.strerror or e})") from e
    except yaml.YAMLError as e:
        raise ParamsFileError(f"{path}: not valid YAML ({yaml_problem(e)})") from e
    values = {name: default for name, (default, _, _) in PARAMS.items()}
    for section in _sections(doc, path):
        for said in not_parameters(section):  # as the node says it (and as rclpy, ignores the name)
            warn(f"{path}: {said}")
        for name, value in section.items():
            if name not in PARAMS:
                continue
            if (why := check_value(name, value)) is not None:
                raise ParamsFileError(f"{path}: {why}")
            values[name] = value
    return values


def rcl_arguments_error(message: str) -> str:
    """rcl's refusal of the ROS arguments (a --params-file it cannot open or parse, a malformed -p or -r), without
    its C source locations, and the forms it takes: rclpy raised it from ``rclpy.init`` as a traceback."""
    said = re.sub(r",? at /\S+:\d+", "", message).replace("failed to initialize rcl: ", "").replace(". Error: error not set", "")
    return f"{said} (the forms: -p name:=value, -r from:=to, --params-file FILE; see nmnet_node --help)"


def params_yaml() -> str:
    """``config/nmnet.yaml``: every node parameter at its default, each with its help as a comment; made from the
    settings vocabulary (``python -m nmnet_ros.interface.params yaml``), a test keeps the shipped file equal to it."""
    lines = ["# nmnet_node parameters at their defaults: ros2 run nmnet_ros nmnet_node --ros-args --params-file "
             "config/nmnet.yaml", "# (made from nmnet_ros/core/settings.py: python -m nmnet_ros.interface.params yaml)",
             "/**:", "  ros__parameters:"]
    for s in NODE:
        note = f"{s.help}" + (f" [{s.allowed()}]" if s.allowed() else "") + (" (startup only)" if s.startup_only else "")
        lines += textwrap.wrap(note, 110, initial_indent="    # ", subsequent_indent="    #   ")
        lines.append(f"    {s.name}: {json.dumps(s.default)}")
    return "\n".join(lines) + "\n"


def settings_table() -> str:
    """The docs' table of every setting: its one name, where it applies, default, range and what it does
    (``python -m nmnet_ros.interface.params markdown``)."""
    rows = ["| Setting | Default | Range | Node parameter | Tool option | What it does |", "|---|---|---|---|---|---|"]
    for s in SETTINGS:
        node = ("yes, at start-up only" if s.startup_only else "yes") if s.node else "no (library)"
        tools = ", ".join(f"{t}" for t in s.tools) or "-"
        option = f"`{s.option}` ({tools})" if s.tools else "-"
        rows.append(f"| `{s.name}` | `{json.dumps(s.default)}` | {s.allowed().replace(' | ', ', ') or '-'} | {node} | {option} | "
                    f"{s.full_help.replace('|', '/')} |")
    return "\n".join(rows) + "\n"


if __name__ == "__main__":
    import sys

    print({"yaml": params_yaml, "markdown": settings_table}[sys.argv[1]](), end="")
