"""Configuration values: every nonsense value is ONE `error:` line naming the key as the user
typed it, exit status 2, nothing written -- at composition, before any terrain or render.

In-process (click's CliRunner), so that each case costs a composition, not an interpreter start."""

import pytest
from click.testing import CliRunner

from helpers.cli import TINY, exr_files

# (overrides, the complete first -- and only -- stderr line)
CASES = {
    # Tracebacks on main:
    "count-not-a-number": (["sweep.cam_azimuth.count=abc"], "error: sweep.cam_azimuth.count=abc: must be an integer"),
    "value-not-a-number": (
        ["sweep.sun_elevation.values=[abc]"],
        "error: sweep.sun_elevation.values=[abc]: element 0 ('abc') must be a number",
    ),
    "fov-not-a-number": (["sweep.fov_deg=wide"], "error: sweep.fov_deg=wide: must be a number"),
    # Silently accepted on main:
    "count-fractional": (["sweep.cam_azimuth.count=1.5"], "error: sweep.cam_azimuth.count=1.5: must be an integer"),
    "appended-typo": (["+render.sampels=4"], "error: render.sampels: unknown key (did you mean render.samples?)"),
    # Messages that named no key, or another key, on main:
    "hapke-not-a-number": (["hapke.w=abc"], "error: hapke.w=abc: must be a number"),
    "seed-not-a-number": (["seed=abc"], "error: seed=abc: must be an integer"),
    # And a few more of the same families:
    "typo-without-plus": (["render.sampels=4"], "error: render.sampels: unknown key (did you mean render.samples?)"),
    "nested-typo": (
        ["+terrain.detail.hurts=0.5"],
        "error: terrain.detail.hurts: unknown key (did you mean terrain.detail.hurst?)",
    ),
    "crater-typo": (
        ["+crater.shackleton.diameter=20"],
        "error: crater.shackleton.diameter: unknown key (did you mean crater.shackleton.diameter_km?)",
    ),
    "bool-not-a-bool": (["render.denoise=maybe"], "error: render.denoise=maybe: must be true or false"),
    "range-after-types": (["terrain.detail.hurst=2"], "error: terrain.detail.hurst=2.0: must lie in (0, 1)"),
    "train-range": (["train.val_fraction=1.5"], "error: train.val_fraction=1.5: must lie in (0, 1)"),
    "budget-cut": (["train.max_train_images=0"], "error: train.max_train_images=0: must be >= 1 (null = all)"),
    "shard-not-a-slice": (["launcher.shard=3"], "error: launcher.shard='3': expected 'i/n', e.g. 0/4"),
}


def _dataset(tmp_path, *overrides):
    from crater_synth.cli import main

    out = tmp_path / "ds"
    result = CliRunner().invoke(main, ["dataset", *TINY, f"data_dir={tmp_path}/data", f"out_dir={out}", *overrides])
    return result, out


@pytest.mark.parametrize("overrides, first_line", CASES.values(), ids=CASES.keys())
def test_bad_value_is_one_line_naming_the_key(tmp_path, overrides, first_line):
    result, out = _dataset(tmp_path, *overrides)
    assert result.exception is None or isinstance(result.exception, SystemExit), result.exception
    assert result.exit_code == 2, (result.stdout, result.stderr)
    assert result.stderr.splitlines() == [first_line]
    assert result.stdout == ""
    assert not out.exists() and not (tmp_path / "data").exists()  # nothing written, not even a directory
    assert not exr_files(out)


@pytest.mark.parametrize("command", ["terrain", "train", "loop", "experiments", "config"])
def test_every_command_validates_at_composition(tmp_path, command):
    """The same one line from every command that composes the configuration (train, loop and
    experiments still take the raw mapping below the CLI, but only after it was validated)."""
    from crater_synth.cli import main

    result = CliRunner().invoke(
        main, [command, f"data_dir={tmp_path}/data", f"run_dir={tmp_path}/run", "sweep.cam_azimuth.count=1.5"]
    )
    assert result.exit_code == 2, result.output
    assert result.stderr.splitlines() == ["error: sweep.cam_azimuth.count=1.5: must be an integer"]
    assert not (tmp_path / "data").exists() and not (tmp_path / "run").exists()


def test_unknown_option_inside_a_crater_list(tmp_path):
    result, _ = _dataset(tmp_path, "crater=[shackleton,atlantis]")
    assert result.exit_code == 2
    from crater_synth.config import CONFIG_DIR

    options = ", ".join(sorted(p.stem for p in (CONFIG_DIR / "crater").glob("*.yaml")))  # both poles + custom
    assert "peary" in options and "shackleton" in options
    assert result.stderr.splitlines() == [f"error: unknown crater 'atlantis' (in crater=[...]): choose from {options}"]


def test_schema_names_are_not_offered_as_options(tmp_path):
    result, _ = _dataset(tmp_path, "render=fancy")
    assert result.exit_code == 2
    assert result.stderr.splitlines() == [
        "error: unknown render 'fancy' (override render=fancy): choose one of cycles_cpu"
    ]


SWEEPS = {
    "comma-list": (["sweep=smoke,demo"], "smoke demo", "sweep=$v"),
    "range": (["render.samples=range(1,3)"], "1 2", "render.samples=$v"),
    "choice": (["sweep=choice(smoke,demo)"], "smoke demo", "sweep=$v"),
    "glob": (["crater=glob(s*)"], "VALUE1 VALUE2", "crater=$v"),
}


@pytest.mark.parametrize("overrides, values, swept", SWEEPS.values(), ids=SWEEPS.keys())
def test_several_values_name_the_loop_that_runs_them(tmp_path, overrides, values, swept):
    """Hydra's multirun is not this CLI's: one line with the shell loop (this command, the other
    overrides as typed), exit 2, nothing written -- not Hydra's hint to add a --multirun we have no option for."""
    result, out = _dataset(tmp_path, *overrides)
    assert result.exit_code == 2, (result.stdout, result.stderr)
    [line] = result.stderr.splitlines()
    rest = " ".join([*TINY, f"data_dir={tmp_path}/data", f"out_dir={out}"])
    assert line.startswith(f"error: {overrides[0]}: several values mean several runs"), line
    assert f"for v in {values}; do crater-synth dataset {rest} {swept}; done" in line, line
    assert "--multirun" not in line
    assert not out.exists() and not (tmp_path / "data").exists()


def test_several_values_refused_from_python_too():
    from crater_synth.config import ConfigError, load_settings

    with pytest.raises(ConfigError, match=r"^sweep=smoke,demo: several values .* for v in smoke demo; do"):
        load_settings(["sweep=smoke,demo"])


@pytest.mark.parametrize(
    "override, key, expected",
    [
        ("crater=[shackleton,faustini]", "craters", ["shackleton", "faustini"]),
        ("sweep.sun_elevation.values=[5,10]", "sun", [5.0, 10.0]),
        ("out_dir='/tmp/a,b'", "out_dir", "/tmp/a,b"),
        ('out_dir="/tmp/c,d"', "out_dir", "/tmp/c,d"),
    ],
)
def test_a_comma_inside_one_value_still_composes(override, key, expected):
    from crater_synth.config import compose

    cfg = compose([override])
    got = {
        "craters": lambda: list(cfg.crater),
        "sun": lambda: list(cfg.sweep.sun_elevation["values"]),
        "out_dir": lambda: cfg.out_dir,
    }[key]()
    assert got == expected
