"""Help: `make help` lists every target with no escape codes when piped; the `crater-synth
--help` one-liners are whole sentences without ``double backticks``; `crater-synth config` prints the
composed configuration."""

import re
import shutil
import subprocess

import pytest
import yaml
from click.testing import CliRunner

from helpers.cli import REPO


def _make_targets() -> set[str]:
    """Every rule of the Makefile a user can run (not files, not variables)."""
    targets = set()
    for line in (REPO / "Makefile").read_text().splitlines():
        m = re.match(r"^([a-zA-Z][a-zA-Z0-9_-]*):(?!=)", line)
        if m:
            targets.add(m.group(1))
    return targets


@pytest.mark.skipif(shutil.which("make") is None, reason="make not installed")
def test_make_help_piped_is_plain_and_complete():
    proc = subprocess.run(
        ["make", "--no-print-directory", "help"], capture_output=True, text=True, cwd=REPO, timeout=60
    )
    assert proc.returncode == 0, proc.stderr
    assert "\x1b" not in proc.stdout
    listed = {line.split()[0] for line in proc.stdout.splitlines() if line.strip()}
    assert listed == _make_targets()
    assert {"verify", "preview", "config"} <= listed


def _help(*args) -> str:
    from crater_synth.cli import main

    res = CliRunner().invoke(main, [*args, "--help"], terminal_width=80)
    assert res.exit_code == 0, res.output
    return res.output


def test_top_level_help_one_liners_are_whole():
    text = _help()
    commands = text.split("Commands:\n", 1)[1].splitlines()
    assert len(commands) >= 12
    for line in commands:
        assert not line.rstrip().endswith("..."), line  # click cuts a too-long first sentence with "..."
        assert line.rstrip().endswith("."), line
    assert "``" not in text and "…" not in text
    names = [line.split()[0] for line in commands]
    assert names[:4] == ["terrain", "catalogue", "fetch-data", "dataset"]  # pipeline order, not A-Z
    assert "config" in names


def test_no_command_help_shows_double_backticks():
    from crater_synth.cli import main

    for name in main.commands:
        text = _help(name)
        assert "``" not in text, (name, text)


def test_config_prints_the_composed_configuration():
    from crater_synth.cli import main

    res = CliRunner().invoke(main, ["config", "sweep=paper", "render.samples=4", "crater=shoemaker"])
    assert res.exit_code == 0, res.output
    cfg = yaml.safe_load(res.stdout)
    assert cfg["render"]["samples"] == 4 and cfg["sweep"]["name"] == "paper"
    assert list(cfg["crater"]) == ["shoemaker"] and cfg["crater"]["shoemaker"]["diameter_km"] == 51.0
    assert cfg["out_dir"].endswith("/synth/paper") and "${" not in res.stdout  # resolved
    one = CliRunner().invoke(main, ["config", "--group", "hapke"])
    assert yaml.safe_load(one.stdout) == {
        "hapke": {"w": 0.32, "xi": -0.25, "b0": 1.0, "h": 0.06, "theta_bar_deg": 23.657}
    }
    bad = CliRunner().invoke(main, ["config", "sweep.fov_deg=wide"])
    assert bad.exit_code == 2 and bad.stderr.splitlines() == ["error: sweep.fov_deg=wide: must be a number"]
