"""The test tiers: `make test` (the fast tier) and `make test-integration` (tests marked `integration`)
split what a plain `pytest` runs, every test but the slow ones, into two parts that do not overlap and
leave nothing out, and CI (.ci/run) runs both. Checked with pytest itself on four stand-in tests, one
per combination of the two markers, under the project's own pytest settings."""

from __future__ import annotations

import re
import subprocess
import sys

from helpers.cli import REPO

STAND_INS = """import pytest


def test_plain():
    pass


@pytest.mark.integration
def test_integration():
    pass


@pytest.mark.slow
def test_slow():
    pass


@pytest.mark.slow
@pytest.mark.integration
def test_slow_integration():
    pass
"""


def _make_variable(name: str) -> str:
    (value,) = re.findall(rf"^{name} := (.+)$", (REPO / "Makefile").read_text(), flags=re.M)
    return value.strip()


def _recipe(target: str) -> str:
    """The first command of a Makefile target."""
    m = re.search(rf"^{re.escape(target)}:[^\n]*\n\t([^\n]+)", (REPO / "Makefile").read_text(), flags=re.M)
    assert m, f"no target {target!r} in the Makefile"
    return m.group(1)


def _selected(tmp_path, *args: str) -> set[str]:
    """The stand-in tests pytest selects with the project's settings (pyproject.toml) and ``args``."""
    (tmp_path / "test_stand_ins.py").write_text(STAND_INS)
    proc = subprocess.run(
        [sys.executable, "-m", "pytest", "-c", str(REPO / "pyproject.toml"), "--rootdir", str(tmp_path)]
        + ["-p", "no:cacheprovider", "--collect-only", "-q", *args, str(tmp_path / "test_stand_ins.py")],
        capture_output=True,
        text=True,
        timeout=120,
        cwd=tmp_path,
    )
    assert proc.returncode == 0, proc.stdout + proc.stderr
    return {line.split("::", 1)[1] for line in proc.stdout.splitlines() if "::" in line}


def test_make_test_and_make_test_integration_split_the_default_run(tmp_path):
    fast, integration = _make_variable("FAST_TESTS"), _make_variable("INTEGRATION_TESTS")
    assert '-m "$(FAST_TESTS)"' in _recipe("test")
    assert '-m "$(INTEGRATION_TESTS)"' in _recipe("test-integration")
    assert _selected(tmp_path) == {"test_plain", "test_integration"}  # plain pytest: all but slow
    assert _selected(tmp_path, "-m", fast) == {"test_plain"}
    assert _selected(tmp_path, "-m", integration) == {"test_integration"}


def test_ci_runs_both_tiers_requiring_blender():
    lines = [line.strip() for line in (REPO / ".ci" / "run").read_text().splitlines()]
    for target in ("test", "test-integration"):
        assert f"CRATER_SYNTH_REQUIRE_BLENDER=1 make {target}" in lines, target


def test_integration_marks_real_tests():
    """The tier is not empty, and every mark is the registered one (--strict-markers refuses a misspelling)."""
    import tomllib

    ini = tomllib.loads((REPO / "pyproject.toml").read_text())["tool"]["pytest"]["ini_options"]
    assert "--strict-markers" in ini["addopts"].split()
    assert any(m.startswith("integration:") for m in ini["markers"])
    tests = [p for p in (REPO / "tests").glob("test_*.py") if p.name != "test_tiers.py"]
    marked = [p.name for p in tests if "pytest.mark.integration" in p.read_text()]
    assert len(marked) >= 5, marked
