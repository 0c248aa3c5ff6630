"""``crater-synth``: one click group; every subcommand takes trailing Hydra overrides.

Entry points stay thin: each subcommand composes the config and calls one function of the module
that owns that pipeline stage. The one-line summaries of ``crater-synth --help`` are written here, in
full (click would cut a docstring's first sentence with "..." to fit the terminal), and help texts
are shown with single backticks (the docstrings' reST ``literals`` would print their double ones).
"""

from __future__ import annotations

import importlib
import json

import click

from crater_synth.cli_common import OVERRIDES, user_errors

# (module, attribute, one-line summary) of each subcommand, in `crater-synth --help` order.
_COMMANDS = (
    ("crater_synth.terrain.patch", "terrain_command", "Build each selected crater's terrain patch."),
    ("crater_synth.terrain.catalogue", "catalogue_command", "Check the catalogue craters against the DEM."),
    ("crater_synth.fetch", "fetch_data_command", "Fetch or check the registered data products."),
    ("crater_synth.dataset.launcher", "dataset_command", "Render the sweep into out_dir (resumable)."),
    ("crater_synth.dataset.verify", "verify_command", "Check a dataset's files against its manifest."),
    ("crater_synth.dataset.preview", "preview_command", "Write a contact sheet PNG per crater."),
    ("crater_synth.dataset.export", "export_command", "Export a dataset to Parquet or WebDataset shards."),
    ("crater_synth.evaluation.classifiers", "train_command", "Train the three classifiers; test on real crops."),
    ("crater_synth.evaluation.classifiers", "evaluate_command", "Evaluate saved models on the real crops."),
    ("crater_synth.evaluation.closed_loop", "loop_command", "Closed loop: add sun elevations until accurate."),
    ("crater_synth.evaluation.figure6", "experiments_command", "Figure 6: accuracy against each sample count."),
    ("crater_synth.evaluation.paper_findings", "results_command", "Check the paper's findings; write docs/results/."),
    ("crater_synth.report", "report_command", "Write the HTML report of a run."),
    ("crater_synth.evaluation.validation", "validate_command", "Validation protocol: choose on validation craters."),
    ("crater_synth.evaluation.ablation", "ablate_command", "Ablation: each fidelity lever turned off in turn."),
    ("crater_synth.evaluation.sunmatch", "sunmatch_command", "Real crops against renders under a dense sun grid."),
    ("crater_synth.navigation.map.cli", "landmarks_command", "Measure the crater landmark map of a polar DEM."),
    (
        "crater_synth.navigation.map.cli",
        "landmarks_check_command",
        "Check a landmark map against two crater lists.",
    ),
    ("crater_synth.navigation.windows.evaluate", "nav_eval_command", "Navigation metrics on real mosaic windows."),
    ("crater_synth.navigation.navigate", "navigate_command", "Detect, identify and fix one nadir frame."),
    (
        "crater_synth.navigation.rendered.frames",
        "nav_frames_command",
        "Render a trajectory's labelled nav frames.",
    ),
    (
        "crater_synth.navigation.rendered.labels",
        "nav_frames_relabel_command",
        "Relabel nav frames (new map).",
    ),
    ("crater_synth.navigation.rendered.cli", "nav_frames_eval_command", "Navigation metrics on rendered frames."),
    (
        "crater_synth.navigation.rendered.lost_in_space",
        "nav_frames_lis_command",
        "Lost in space on rendered frames (no position prior).",
    ),
    (
        "crater_synth.navigation.rendered.detector_train",
        "nav_detector_frames_command",
        "Render the learned crater detector's training frames.",
    ),
    (
        "crater_synth.navigation.rendered.detector_train",
        "nav_detector_train_command",
        "Train the learned crater detector.",
    ),
    ("crater_synth.bench.cli", "bench_command", "Benchmarks: rendering, training, navigation, export."),
    ("crater_synth.cli", "config_command", "Print the composed configuration (YAML)."),
)


def _readable(text: str | None) -> str | None:
    """Help text as printed: ``literal`` -> `literal`."""
    return text.replace("``", "`") if text else text


class _InOrder(click.Group):
    """Lists the subcommands in pipeline order (terrain -> dataset -> train -> report), not A-Z."""

    def list_commands(self, ctx):
        return list(self.commands)


@click.group(cls=_InOrder, context_settings={"help_option_names": ["-h", "--help"], "max_content_width": 100})
def main():
    """DEM-synthesised lunar crater images: terrain, rendering, training, closed loop.

    Every subcommand accepts Hydra overrides, e.g.
    `crater-synth terrain crater=shoemaker terrain.detail.enabled=false`;
    `crater-synth config [OVERRIDES]...` prints what they compose to.
    """


@click.command("config")
@OVERRIDES
@click.option("--group", "-g", default=None, metavar="GROUP", help="Print only this group (e.g. render).")
@click.option("--json", "as_json", is_flag=True, help="JSON instead of YAML.")
@user_errors
def config_command(overrides, group, as_json):
    """Print the composed configuration: configs/ with these overrides, validated and resolved.

    The values every command would run with (Hydra's `--cfg job`), e.g.
    `crater-synth config sweep=paper render.samples=4 --group render`.
    """
    import yaml

    from crater_synth.config import ConfigError, load_settings

    data = load_settings(overrides).as_dict()
    if group is not None:
        if group not in data:
            raise ConfigError(f"--group {group}: no such group; choose one of {', '.join(data)}")
        data = {group: data[group]}
    click.echo(json.dumps(data, indent=1) if as_json else yaml.safe_dump(data, sort_keys=False).rstrip())


for _module, _attr, _summary in _COMMANDS:
    _cmd = config_command if _attr == "config_command" else getattr(importlib.import_module(_module), _attr)
    _cmd.short_help = _summary
    _cmd.help = _readable(_cmd.help)
    main.add_command(_cmd)


if __name__ == "__main__":  # pragma: no cover
    main()
