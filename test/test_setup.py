"""`make setup` takes torch's CPU build: the Makefile's cpu-torch step, run against local package indexes.

PyTorch's CPU index cannot be reached from the test machines, so two small stand-in wheels of the pinned
version play its two builds: ``+cpu`` behind ``TORCH_INDEX`` (as on download.pytorch.org/whl/cpu) and the
plain version on the default index (as PyPI's, which on Linux pulls the CUDA libraries)."""

from __future__ import annotations

import os
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PIN = next(line.split("==")[1].strip() for line in (ROOT / "requirements.txt").read_text().splitlines()
           if line.startswith("torch=="))


def _stand_in_wheel(folder: Path, version: str) -> None:
    """A wheel named torch, of ``version``, that installs one empty module, and the folder's index page (PEP 503)."""
    folder.mkdir(parents=True, exist_ok=True)
    info = f"torch-{version}.dist-info"
    files = {"torch/__init__.py": "",
             f"{info}/METADATA": f"Metadata-Version: 2.1\nName: torch\nVersion: {version}\n",
             f"{info}/WHEEL": "Wheel-Version: 1.0\nGenerator: test\nRoot-Is-Purelib: true\nTag: py3-none-any\n"}
    files[f"{info}/RECORD"] = "".join(f"{name},,\n" for name in [*files, f"{info}/RECORD"])
    with zipfile.ZipFile(folder / f"torch-{version}-py3-none-any.whl", "w") as z:
        for name, text in files.items():
            z.writestr(name, text)
    wheel = f"torch-{version}-py3-none-any.whl"
    (folder / "index.html").write_text(f'<!DOCTYPE html><html><body><a href="{wheel}">{wheel}</a></body></html>')


@pytest.fixture(scope="module")
def venv(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("venv")
    subprocess.run([sys.executable, "-m", "venv", "--clear", str(path)], check=True, capture_output=True)
    return path


def _cpu_torch(venv: Path, index: str, find_links: Path | None) -> subprocess.CompletedProcess:
    env = {**os.environ, "PIP_CONFIG_FILE": os.devnull, "PIP_FIND_LINKS": str(find_links or ""), "PIP_NO_INDEX": "0"}
    env = {k: v for k, v in env.items() if k not in ("PIP_EXTRA_INDEX_URL", "PIP_INDEX_URL", "PIP_CONSTRAINT", "MAKEFLAGS")}
    subprocess.run([venv / "bin" / "pip", "uninstall", "-y", "-q", "torch"], capture_output=True, env=env)
    return subprocess.run(["make", "--no-print-directory", "-C", str(ROOT), "cpu-torch", f"VENV={venv}", f"TORCH_INDEX={index}"],
                          capture_output=True, text=True, env=env, timeout=300)


def _notes(done: subprocess.CompletedProcess) -> list[str]:
    """The lines the step printed as a note (make also echoes the command, which holds the text)."""
    return [line for line in done.stdout.splitlines() if line.startswith("note:")]


def _installed(venv: Path) -> str | None:
    out = subprocess.run([venv / "bin" / "python", "-c", "import importlib.metadata as m; print(m.version('torch'))"],
                         capture_output=True, text=True)
    return out.stdout.strip() if out.returncode == 0 else None


def test_setup_installs_torch_from_the_cpu_index_before_the_requirements():
    """The set-up recipe runs cpu-torch, with the pin read from requirements.txt, before requirements.txt."""
    out = subprocess.run(["make", "-n", "-B", "-C", str(ROOT), "setup", "VENV=/nonexistent/venv"], capture_output=True,
                         text=True, check=True).stdout
    torch_at = out.index(f'--index-url https://download.pytorch.org/whl/cpu "torch=={PIN}"')
    assert torch_at < out.index("pip install --quiet -r requirements.txt")


def test_cpu_build_wins_over_the_default_indexs_build(venv, tmp_path):
    _stand_in_wheel(tmp_path / "cpu" / "torch", f"{PIN}+cpu")
    _stand_in_wheel(tmp_path / "default", PIN)
    done = _cpu_torch(venv, (tmp_path / "cpu").as_uri(), tmp_path / "default")
    assert done.returncode == 0, done.stdout + done.stderr
    assert _installed(venv) == f"{PIN}+cpu"
    assert not _notes(done)


def test_without_the_cpu_index_setup_goes_on_and_says_where_torch_comes_from(venv, tmp_path):
    (tmp_path / "empty").mkdir()
    done = _cpu_torch(venv, (tmp_path / "empty").as_uri(), None)
    assert done.returncode == 0, done.stdout + done.stderr
    assert _installed(venv) is None
    (note,) = _notes(done)
    assert note.startswith(f"note: torch=={PIN} is not at {(tmp_path / 'empty').as_uri()}") and "CUDA" in note


def test_an_empty_torch_index_skips_the_step(venv):
    done = _cpu_torch(venv, "", None)
    assert done.returncode == 0 and "pip" not in done.stdout and _installed(venv) is None
