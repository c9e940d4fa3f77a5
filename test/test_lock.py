"""requirements.txt pins everything the direct pins bring in (scripts/lock.py, `make lock`)."""

from __future__ import annotations

import importlib.util
from importlib.metadata import version

import pytest
from packaging.requirements import Requirement
from packaging.utils import canonicalize_name

from .conftest import ROOT

spec = importlib.util.spec_from_file_location("lock", ROOT / "scripts" / "lock.py")
lock = importlib.util.module_from_spec(spec)
spec.loader.exec_module(lock)


def pins(text: str) -> dict[str, str]:
    reqs = [Requirement(line.split("#")[0]) for line in text.splitlines() if line.strip() and not line.startswith("#")]
    return {canonicalize_name(r.name): str(r.specifier) for r in reqs}


def test_every_installed_dependency_of_the_pins_is_pinned_at_its_installed_version():
    text = (ROOT / "requirements.txt").read_text()
    direct = [Requirement(line.split("#")[0]) for line in text.split(lock.MARKER)[0].splitlines()
              if line.strip() and not line.startswith("#")]
    pinned = pins(text)
    found = lock.closure(direct)
    missing = sorted(name for name in found if name not in pinned)
    assert not missing, f"not pinned in requirements.txt (run `make lock`): {missing}"
    for name, (installed, _) in found.items():
        assert pinned[name] == f"=={installed.split('+')[0]}", name


def test_lock_writes_the_section_below_the_pins_and_a_second_run_changes_nothing(tmp_path):
    req = tmp_path / "requirements.txt"
    req.write_text(f"# tests\npytest=={version('pytest')}\n")
    lock.main(req)
    first = req.read_text()
    assert first.startswith(f"# tests\npytest=={version('pytest')}\n\n{lock.MARKER}\n")
    assert pins(first)["pluggy"] == f"=={version('pluggy')}" and pins(first)["iniconfig"] == f"=={version('iniconfig')}"
    lock.main(req)
    assert req.read_text() == first


def test_a_pin_that_is_not_installed_is_named_with_what_to_do(tmp_path):
    req = tmp_path / "requirements.txt"
    req.write_text("no-such-package-nmnet==1.0\n")
    with pytest.raises(SystemExit, match="no-such-package-nmnet is required but not installed: run `make setup`"):
        lock.main(req)
