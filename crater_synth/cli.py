"""``crater-synth``: one click group; every subcommand takes trailing Hydra overrides.

Entry points stay thin: each subcommand composes the config and calls one function of the module
that owns that pipeline stage. The group is lazy: ``crater-synth --help`` reads :data:`COMMANDS` (name,
where the command lives, one-line summary, by stage) and imports no command module; a command's module
is imported only when that command runs or shows its own help, so the modules import what they need at
their top and start-up stays fast. The one-line summaries are written here, in full (click would cut a
docstring's first sentence with "..." to fit the terminal), and help texts are shown with single
backticks (the docstrings' reST ``literals`` would print their double ones).
"""

from __future__ import annotations

import importlib

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
            f"{_NAV}.rendered.detector_train:nav_detector_train_command",
            "Train the learned crater detector.",
        ),
    ),
    "tools": (
        ("bench", "crater_synth.bench.cli:bench_command", "Benchmarks: rendering, training, navigation, export."),
        ("config", "crater_synth.config_cli:config_command", "Print the composed configuration (YAML)."),
    ),
}
_WHERE = {name: where for entries in COMMANDS.values() for name, where, _ in entries}
_SUMMARY = {name: summary for entries in COMMANDS.values() for name, _, summary in entries}


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
            cmd = getattr(importlib.import_module(module), attr)
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
