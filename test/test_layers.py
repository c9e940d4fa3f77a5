"""The package's architecture, checked: each layer imports only the layers below it, no module imports itself back
through others, and the perception core loads neither ROS nor a bag library."""

from __future__ import annotations

import ast
import subprocess
import sys

from .conftest import ROOT

PKG = ROOT / "nmnet_ros"
LAYERS = ["core", "interface", "io", "ros", "tools"]  # bottom to top; nmnet_ros.node (python -m) sits above them


def module_name(path) -> str:
    parts = path.relative_to(ROOT).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def layer(module: str) -> int:
    """The layer's rank: 0 for the package's own __init__, len(LAYERS) + 1 for the top-level entry modules."""
    parts = module.split(".")
    if len(parts) == 1:
        return 0
    return LAYERS.index(parts[1]) + 1 if parts[1] in LAYERS else len(LAYERS) + 1


def imports() -> dict[str, set[str]]:
    """Every module of the package and the package modules it imports anywhere (function-level imports too)."""
    graph: dict[str, set[str]] = {}
    for path in PKG.rglob("*.py"):
        name = module_name(path)
        package = name if path.name == "__init__.py" else name.rpartition(".")[0]
        found = set()
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ImportFrom):
                base = package.split(".")[: len(package.split(".")) - node.level + 1] if node.level else []
                target = ".".join([*base, *([node.module] if node.module else [])])
                for alias in node.names:  # `from . import asl` names modules
                    candidate = f"{target}.{alias.name}"
                    found.add(candidate if (PKG.parent / (candidate.replace(".", "/") + ".py")).exists() else target)
            elif isinstance(node, ast.Import):
                found.update(a.name for a in node.names)
        graph[name] = {m for m in found if m.split(".")[0] == "nmnet_ros" and m != name}
    return graph


def test_each_layer_imports_only_the_layers_below_it():
    graph = imports()
    assert {m.split(".")[1] for m in graph if m.count(".") >= 2} == set(LAYERS)  # every module sits in a layer
    upward = [f"{a} imports {b}" for a, deps in graph.items() for b in deps if layer(b) > layer(a)]
    assert not upward, "\n".join(upward)


def test_no_import_cycle():
    graph = imports()
    state: dict[str, int] = {}  # 1: on the path, 2: done

    def visit(m: str, path: list[str]) -> list[str] | None:
        state[m] = 1
        for d in sorted(graph.get(m, ())):
            if state.get(d) == 1:
                return [*path, m, d]
            if d not in state and (cycle := visit(d, [*path, m])):
                return cycle
        state[m] = 2
        return None

    for m in sorted(graph):
        if m not in state and (cycle := visit(m, [])):
            raise AssertionError("import cycle: " + " -> ".join(cycle[cycle.index(cycle[-1]):]))


def test_the_core_and_the_interface_load_no_ros_and_no_bag_library():
    core = [module_name(p) for p in (PKG / "core").glob("*.py")] + [module_name(p) for p in (PKG / "interface").glob("*.py")]
    code = "import sys\n" + "".join(f"import {m}\n" for m in core) + (
        "print(sorted({m.split('.')[0] for m in sys.modules} & {'rclpy', 'rosbags', 'mcap', 'sensor_msgs'}))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, cwd=ROOT).stdout.strip()
    assert out == "[]", out


def test_a_back_ends_names_import_from_the_package_without_ros():
    code = ("import sys\nfrom nmnet_ros import LARGE_FRAMES_PROFILE, estimate_of_message, matches_of_cloud\n"
            "assert LARGE_FRAMES_PROFILE.is_file()\nprint('rclpy' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, cwd=ROOT).stdout.strip()
    assert out == "False"
