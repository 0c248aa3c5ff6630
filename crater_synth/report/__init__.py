"""``crater-synth report RUN_DIR``: one self-contained HTML page summarising a run (docs/report.md).

Writes ``RUN_DIR/report/index.html`` plus its PNGs (relative links only: no external URL, no script),
built in a temporary directory inside RUN_DIR and swapped into place, so a reader never sees half a
report. Sections: contact sheets per crater; a real WAC crop beside the closest synthetic render;
input histograms real vs synthetic; the classifiers' accuracies and confusion matrices; the closed-loop
history; the Figure 6 experiments; provenance and the limits of the test set. Works for any number of
classes (craters).

A missing input turns its section into a plain "not run: <what produces it>" note; a corrupt input
is one :class:`ReportError` naming the file. Never imports torch.

Layout: ``inputs`` (loaders, validation, effective configuration) -> ``gather`` (one function per
section: data for its template, figures drawn by ``figures``) -> ``page`` (Jinja2 over
``templates/*.html.j2``) -> ``build`` (validation up front, atomic publication by ``publish``).
"""

from crater_synth.report.build import INDEX_FILE, REPORT_DIR, build_report, report_command
from crater_synth.report.inputs import ReportError, RunConfig, effective_config

__all__ = ["INDEX_FILE", "REPORT_DIR", "ReportError", "RunConfig", "build_report", "effective_config", "report_command"]
