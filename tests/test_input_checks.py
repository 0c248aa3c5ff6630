"""Inputs refused in one line before any work: names that become file or folder names (crater, sweep,
trajectory) that are not plain names (crater_core.typed_config.need_plain_name: no "/", "..", leading dot);
an empty ``nav-frames --frames`` list; a ``bench`` override typo."""

from __future__ import annotations

import pytest
from click.testing import CliRunner

from crater_core.typed_config import PLAIN_NAME
from crater_synth.cli import main
from crater_synth.config import load_settings
from crater_synth.errors import ConfigError


@pytest.mark.parametrize("bad", ["../escape", "a/b", ".hidden", "", "x" * 65, "sp ace", "dot.dot"])
@pytest.mark.parametrize(
    "overrides, key",
    [
        (["crater=custom", "crater.custom.lat=-85", "crater.custom.lon=10", "crater.custom.diameter_km=20"], "crater"),
        ([], "sweep"),
        (["trajectory=descent_ridge"], "trajectory"),
    ],
)
def test_a_name_that_is_not_plain_is_refused(bad, overrides, key):
    name_key = "crater.custom.name" if key == "crater" else f"{key}.name"
    with pytest.raises(ConfigError, match=name_key.replace(".", r"\.")):
        load_settings([*overrides, f"{name_key}={bad!r}" if bad else f"{name_key}=''"])


def test_the_committed_names_are_plain():
    s = load_settings(["trajectory=descent_ridge"])
    assert all(PLAIN_NAME.fullmatch(c.name) for c in s.craters) and PLAIN_NAME.fullmatch(s.sweep.name)


def test_the_dataset_command_refuses_an_escaping_crater_name_and_writes_nothing(tmp_path):
    r = CliRunner().invoke(
        main,
        [
            "dataset",
            "crater=custom",
            "crater.custom.name=../escape",
            "crater.custom.lat=-85",
            "crater.custom.lon=10",
            "crater.custom.diameter_km=20",
            f"data_dir={tmp_path / 'data'}",
            f"out_dir={tmp_path / 'out'}",
        ],
    )
    assert r.exit_code != 0 and "crater.custom.name" in r.output and len(r.output.strip().splitlines()) == 1
    assert not any(tmp_path.iterdir())


@pytest.mark.parametrize("frames", ["", " , "])
def test_nav_frames_refuses_an_empty_frame_list(tmp_path, frames):
    r = CliRunner().invoke(
        main, ["nav-frames", "trajectory=descent_ridge", "--out", str(tmp_path / "f"), "--frames", frames]
    )
    assert r.exit_code == 2 and "names no frame" in r.output and len(r.output.strip().splitlines()) == 1
    assert not (tmp_path / "f").exists()


def test_bench_refuses_an_override_typo_before_any_part_runs():
    r = CliRunner().invoke(main, ["bench", "--part", "opencv", "render.wrokers=2"])
    assert r.exit_code == 2 and "wrokers" in r.output and len(r.output.strip().splitlines()) == 1
