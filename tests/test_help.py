"""Help: `make help` lists every target with no escape codes when piped; the `crater-synth
--help` one-liners are whole sentences without ``double backticks``; `crater-synth config` prints the
composed configuration."""

import re
import shutil
import subprocess
import sys

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


def _sections(text: str) -> dict[str, list[str]]:
    """The command lines of `crater-synth --help` under each heading (the lines after "Options:")."""
    sections: dict[str, list[str]] = {}
    heading = None
    for line in text.split("Options:\n", 1)[1].splitlines():
        if line and not line.startswith(" "):
            heading = line.rstrip(":")
            sections[heading] = []
        elif line.strip() and heading is not None and heading != "Options":
            sections[heading].append(line)
    return sections


def test_top_level_help_lists_commands_by_stage_with_whole_one_liners():
    from crater_synth.cli import main

    text = _help()
    sections = _sections(text)
    assert list(sections) == ["Data", "Rendering", "Training", "Evaluation", "Navigation", "Tools"]
    lines = [line for rows in sections.values() for line in rows]
    for line in lines:
        assert not line.rstrip().endswith("..."), line  # click cuts a too-long first sentence with "..."
        assert line.rstrip().endswith("."), line
    assert "``" not in text and "…" not in text
    names = {heading: [line.split()[0] for line in rows] for heading, rows in sections.items()}
    assert names["Data"] == ["fetch-data", "terrain", "catalogue"]  # pipeline order, not A-Z
    assert names["Rendering"][0] == "dataset" and names["Training"] == ["train", "evaluate"]
    assert "config" in names["Tools"] and "navigate" in names["Navigation"]
    assert sorted(n for rows in names.values() for n in rows) == sorted(main.list_commands(None))
    assert len({line.index(line.split()[1]) for line in lines}) == 1  # one column of summaries


def test_help_imports_no_command_module():
    """`crater-synth --help` reads the table in cli.py: no command module (and none of the heavy
    libraries they import at their top) is loaded, so start-up stays fast."""
    code = (
        "import sys; from click.testing import CliRunner; from crater_synth.cli import main; "
        "r = CliRunner().invoke(main, ['--help']); assert r.exit_code == 0, r.output; "
        "print(' '.join(sorted(m for m in sys.modules if m.startswith(('crater_synth.', 'train', 'numpy', "
        "'omegaconf', 'hydra', 'torch', 'scipy', 'matplotlib')))))"
    )
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=REPO, timeout=120)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.split() == ["crater_synth.cli"], proc.stdout


def test_every_listed_command_loads_under_its_name():
    """Each row of the table names a click command of that name (loaded when asked for)."""
    from crater_synth.cli import COMMANDS, main

    for entries in COMMANDS.values():
        for name, where, summary in entries:
            cmd = main.get_command(None, name)
            assert cmd is not None and cmd.name == name, (name, where)
            assert cmd.short_help == summary
    assert main.get_command(None, "no-such-command") is None


def test_no_command_help_shows_double_backticks():
    from crater_synth.cli import main

    for name in main.list_commands(None):
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
