"""`pip install` of the package's wheel brings what it needs: a fresh venv, the wheel and its declared dependencies
(held to requirements.txt's versions, so torch is the CPU build the lock names), then ``nmnet replay`` on the
bundled sample bag. It died with ``No module named 'numpy'`` when the package declared no dependencies."""

from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
import sys

import pytest

from .conftest import ROOT

pytestmark = pytest.mark.slow


def test_the_wheel_installs_with_its_dependencies_and_replays_the_sample(tmp_path):
    src = tmp_path / "src"  # built from a copy: setuptools writes build/ next to the sources
    shutil.copytree(ROOT, src, ignore=shutil.ignore_patterns(".*", "build", "*.egg-info", "__pycache__", "docs", "test",
                                                             "nmnet_demo"))
    subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation", "-q", "-w", str(tmp_path),
                    str(src)], check=True, capture_output=True, cwd=tmp_path)
    (wheel,) = tmp_path.glob("nmnet_ros-*.whl")
    venv = tmp_path / "venv"
    subprocess.run([sys.executable, "-m", "venv", str(venv)], check=True, capture_output=True)
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "VIRTUAL_ENV", "MAKEFLAGS")}
    lock = tmp_path / "constraints.txt"  # the lock's versions; pip takes no extras in a constraint
    lock.write_text(re.sub(r"\[[^\]]*\]", "", (ROOT / "requirements.txt").read_text()))
    done = subprocess.run([venv / "bin" / "pip", "install", "-q", "-c", str(lock), str(wheel)],
                          capture_output=True, text=True, env=env, timeout=1200)
    assert done.returncode == 0, done.stderr[-3000:]
    out = tmp_path / "run"
    r = subprocess.run([venv / "bin" / "nmnet", "replay", str(ROOT / "nmnet_ros" / "sample" / "kitti07_120-159"), "--out",
                        str(out / "o.mcap"), "--json", str(out / "s.json"), "--duration", "0.5", "--no-progress"],
                       capture_output=True, text=True, env=env, cwd=tmp_path, timeout=600)
    assert r.returncode == 0, r.stderr[-3000:]
    summary = json.loads((out / "s.json").read_text())
    assert summary["processed"] == summary["frames"] > 1 and summary["scored_pairs"] > 0, summary
    imported = subprocess.run([venv / "bin" / "python", "-c", "import nmnet_ros.tools.replay, sys; print(sys.prefix)"],
                              capture_output=True, text=True, env=env, cwd=tmp_path, check=True).stdout.strip()
    assert imported == str(venv)  # the installed package ran, not the source tree
