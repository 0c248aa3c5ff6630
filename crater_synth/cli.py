"""``crater-synth``: one click group; every subcommand takes trailing Hydra overrides.

Entry points stay thin: each subcommand composes the config and calls one function of the module
that owns that pipeline stage. The group is lazy: ``crater-synth --help`` reads :data:`COMMANDS` (name,
where the command lives, one-line summary, by stage) and imports no command module; a command's module
is imported only when that command runs or shows its own help, so the modules import what they need at
their top and start-up stays fast. The one-line summaries are written here, in full (click would cut a
docstring's first sentence with "..." to fit the terminal), and help texts are shown with single
backticks (the docstrings' reST ``literals`` would print their double ones).

The base install runs only ``config`` and ``fetch-data``; every other command needs a pip extra
(:data:`COMMAND_EXTRA`, docs/install.md). Before a command runs, the loader checks that its extra's
modules are installed, so a missing one ends it at once (not after an hour of rendering) with one line
naming the extra and the pip command that adds it; a module missing at import or at run time (Dask, for
``launcher=dask``) gets the same line.
"""

from __future__ import annotations

import functools
import importlib
import importlib.util
import os
import sys

import click

_NAV = "crater_synth.navigation"
# Every subcommand by stage, the stages in pipeline order (the headings of `crater-synth --help`):
# (name, "module:attribute" of its click command, one-line summary).
COMMANDS: dict[str, tuple[tuple[str, str, str], ...]] = {
    "data": (
        ("fetch-data", "crater_synth.fetch:fetch_data_command", "Fetch or check the registered data products."),
        ("terrain", "crater_synth.terrain.patch:terrain_command", "Build each selected crater's terrain patch."),
        (
            "catalogue",
            "crater_synth.terrain.catalogue:catalogue_command",
            "Check the catalogue craters against the DEM.",
        ),
    ),
    "rendering": (
        ("dataset", "crater_synth.dataset.launcher:dataset_command", "Render the sweep into out_dir (resumable)."),
        ("verify", "crater_synth.dataset.verify:verify_command", "Check a dataset's files against its manifest."),
        ("preview", "crater_synth.dataset.preview:preview_command", "Write a contact sheet PNG per crater."),
        ("export", "crater_synth.dataset.export:export_command", "Export a dataset to Parquet or WebDataset shards."),
        (
            "detection-frames",
            "crater_synth.dataset.detection_cli:detection_frames_command",
            "Render labelled frames of procedural crater fields.",
        ),
    ),
    "training": (
        (
            "train",
            "crater_synth.evaluation.classifiers:train_command",
            "Train the three classifiers; test on real crops.",
        ),
        (
            "evaluate",
            "crater_synth.evaluation.classifiers:evaluate_command",
            "Evaluate saved models on the real crops.",
        ),
    ),
    "evaluation": (
        ("loop", "crater_synth.evaluation.closed_loop:loop_command", "Closed loop: add sun elevations until accurate."),
        (
            "experiments",
            "crater_synth.evaluation.figure6:experiments_command",
            "Figure 6: accuracy against each sample count.",
        ),
        (
            "results",
            "crater_synth.evaluation.paper_findings:results_command",
            "Check the paper's findings in a Figure 6 run.",
        ),
        (
            "validate",
            "crater_synth.evaluation.validation:validate_command",
            "Validation protocol: choose on validation craters.",
        ),
        (
            "ablate",
            "crater_synth.evaluation.ablation:ablate_command",
            "Ablation: each fidelity lever turned off in turn.",
        ),
        (
            "sunmatch",
            "crater_synth.evaluation.sunmatch:sunmatch_command",
            "Real crops against renders under a dense sun grid.",
        ),
        ("report", "crater_synth.report:report_command", "Write the HTML report of a run."),
    ),
    "navigation": (
        ("landmarks", f"{_NAV}.map.cli:landmarks_command", "Measure the crater landmark map of a polar DEM."),
        (
            "landmarks-check",
            f"{_NAV}.map.cli:landmarks_check_command",
            "Check a landmark map against two crater lists.",
        ),
        ("nav-eval", f"{_NAV}.windows.evaluate:nav_eval_command", "Navigation metrics on real mosaic windows."),
        ("navigate", f"{_NAV}.navigate:navigate_command", "Detect, identify and fix one nadir frame."),
        ("detect", f"{_NAV}.detect_cmd:detect_command", "Find craters in an image or a folder of images."),
        ("nav-frames", f"{_NAV}.rendered.frames:nav_frames_command", "Render a trajectory's labelled nav frames."),
        ("nav-frames-relabel", f"{_NAV}.rendered.labels:nav_frames_relabel_command", "Relabel nav frames (new map)."),
        ("nav-frames-eval", f"{_NAV}.rendered.cli:nav_frames_eval_command", "Navigation metrics on rendered frames."),
        (
            "nav-frames-lis",
            f"{_NAV}.rendered.lost_in_space:nav_frames_lis_command",
            "Lost in space on rendered frames (no position prior).",
        ),
        (
            "nav-detector-frames",
            f"{_NAV}.rendered.detector_train:nav_detector_frames_command",
            "Render the learned crater detector's training frames.",
        ),
        (
            "nav-detector-train",
            f"{_NAV}.train_cmd:nav_detector_train_command",
            "Train the learned crater detector.",
        ),
        (
            "nav-verifier-train",
            f"{_NAV}.rendered.verifier_train:nav_verifier_train_command",
            "Train the learned detector's second stage (the verifier).",
        ),
    ),
    "tools": (
        ("bench", "crater_synth.bench.cli:bench_command", "Benchmarks: rendering, training, navigation, export."),
        ("config", "crater_synth.config_cli:config_command", "Print the composed configuration (YAML)."),
    ),
}
# The top-level modules each pip extra (pyproject.toml [project.optional-dependencies]) brings that the
# project imports, and the extra each command needs; tests/test_declared_deps.py checks both tables against
# pyproject.toml and the commands' imports.
_RENDER = (
    "bpy",
    "OpenImageIO",
    "OpenEXR",
    "rasterio",
    "affine",
    "scipy",
    "skimage",
    "matplotlib",
    "PIL",
    "tqdm",
    "cv2",
)
EXTRA_MODULES: dict[str, tuple[str, ...]] = {
    "render": _RENDER,
    "train": (*_RENDER, "torch", "torchvision", "sklearn", "joblib", "jinja2", "markupsafe", "pyarrow"),
    "nav": (*_RENDER, "torch", "torchvision"),
    "export": (*_RENDER, "pyarrow"),
    "dask": (*_RENDER, "distributed"),
}
EXTRA_MODULES["all"] = tuple(sorted({m for modules in EXTRA_MODULES.values() for m in modules}))
_TRAIN = ("train", "evaluate", "loop", "experiments", "results", "validate", "ablate", "sunmatch", "report")
COMMAND_EXTRA: dict[str, str] = {
    **dict.fromkeys(("terrain", "catalogue", "dataset", "verify", "preview", "detection-frames"), "render"),
    "export": "export",
    **dict.fromkeys(_TRAIN, "train"),
    **{name: "nav" for name, _, _ in COMMANDS["navigation"]},
    "bench": "all",
}
# `bench --part P` needs P's extra only (crater_synth/bench/cli.py): a GPU host with the nav extra runs the
# detector part without Dask.
BENCH_PART_EXTRA: dict[str, str] = {
    "renderer": "render",
    "detection-frames": "render",
    "train": "train",
    "distributed": "dask",
    "export": "export",
    **dict.fromkeys(("navigation", "navframes", "detector", "detector-layout", "detect", "opencv"), "nav"),
}
# Not checked before a command runs: a Blender binary (render.blender=...) stands in for the pip bpy module.
_NOT_PROBED = {"bpy"}
_EXIT_MISSING_EXTRA = 2  # as an environment error of a running command (cli_common)
_WHERE = {name: where for entries in COMMANDS.values() for name, where, _ in entries}
_SUMMARY = {name: summary for entries in COMMANDS.values() for name, _, summary in entries}


def _install_command(extra: str) -> str:
    """The pip command that adds ``extra``: editable from the checkout this code runs from, as ``make setup``
    installs it (an install from a wheel names no checkout: docs/install.md)."""
    root = os.path.dirname(os.path.dirname(os.path.realpath(__file__)))
    if not os.path.isfile(os.path.join(root, "pyproject.toml")):
        root = "<the crater-synth checkout>"
    return f"pip install -e '{root}[{extra}]'"


def missing_extra(command: str, module: str | None, extra: str | None = None) -> str | None:
    """The one line for ``command`` whose import or run found ``module`` missing, or None when that module
    belongs to no extra (a bug, not an install to complete). ``extra``: the one this run needs, where not
    the command's (``bench --part P``)."""
    top = (module or "").split(".")[0]
    extra = extra or COMMAND_EXTRA.get(command)
    if top not in EXTRA_MODULES.get(extra or "", ()):  # e.g. Dask for `dataset launcher=dask`
        extra = min(
            (e for e, mods in EXTRA_MODULES.items() if top in mods), key=lambda e: len(EXTRA_MODULES[e]), default=None
        )
    if extra is None:
        return None
    return f"`crater-synth {command}` needs the {extra} extra ({top} is not installed): {_install_command(extra)}"


def _exit_missing(command: str, exc: ModuleNotFoundError, extra: str | None = None) -> None:
    """Exit with the missing-extra line when ``exc`` is a module of an extra; otherwise re-raise it."""
    line = missing_extra(command, exc.name, extra)
    if line is None:
        raise exc
    click.echo(f"error: {line}", err=True)
    sys.exit(_EXIT_MISSING_EXTRA)


def _with_extra(command: str, callback):
    """``callback`` run only when ``command``'s extra is installed, a module missing while it runs turned
    into the missing-extra line (the help was shown before: it needs no extra)."""

    @functools.wraps(callback)
    def run(*args, **kwargs):
        extra = COMMAND_EXTRA.get(command, "")
        if command == "bench":
            extra = BENCH_PART_EXTRA.get(kwargs.get("part", "all"), extra)
        try:
            for module in EXTRA_MODULES.get(extra, ()):
                if module not in _NOT_PROBED and importlib.util.find_spec(module) is None:
                    raise ModuleNotFoundError(f"No module named {module!r}", name=module)
            return callback(*args, **kwargs)
        except ModuleNotFoundError as exc:
            _exit_missing(command, exc, extra)

    return run


def _readable(text: str | None) -> str | None:
    """Help text as printed: ``literal`` -> `literal`."""
    return text.replace("``", "`") if text else text


class LazyGroup(click.Group):
    """Lists :data:`COMMANDS` under their stages and imports a command's module only to run it (or to
    show its own help)."""

    def list_commands(self, ctx):
        return list(_WHERE)

    def get_command(self, ctx, cmd_name):
        if cmd_name not in _WHERE:
            return None
        if cmd_name not in self.commands:
            module, attr = _WHERE[cmd_name].split(":")
            try:
                cmd = getattr(importlib.import_module(module), attr)
            except ModuleNotFoundError as exc:  # a library the command's module imports at its top
                _exit_missing(cmd_name, exc)
            cmd.callback = _with_extra(cmd_name, cmd.callback)
            cmd.short_help = _SUMMARY[cmd_name]
            cmd.help = _readable(cmd.help)
            self.add_command(cmd, cmd_name)
        return self.commands[cmd_name]

    def format_commands(self, ctx, formatter):
        """One section per stage, from the table (no module imported), the summaries in one column."""
        width = max(map(len, _WHERE))
        for stage, entries in COMMANDS.items():
            with formatter.section(stage.capitalize()):
                formatter.write_dl([(name.ljust(width), summary) for name, _, summary in entries])


@click.group(cls=LazyGroup, context_settings={"help_option_names": ["-h", "--help"], "max_content_width": 100})
def main():
    """DEM-synthesised lunar crater images: terrain, rendering, training, closed loop.

    Every subcommand accepts Hydra overrides, e.g.
    `crater-synth terrain crater=shoemaker terrain.detail.enabled=false`;
    `crater-synth config [OVERRIDES]...` prints what they compose to.
    """


if __name__ == "__main__":  # pragma: no cover
    main()
