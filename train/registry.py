"""The one list of classifiers (docs/classifiers.md): their keys, names, colours and saved files.

Training, evaluation, the closed loop, the Figure 6 experiments, the report and the tests all read the
models from here. Deliberately light (stdlib only, no torch): the report and the CLI import it freely.
Adding a classifier: add a :class:`ModelSpec`, train/save it in ``train.trainer.train_all`` and predict
with it in ``train.evaluate.evaluate_run`` (which refuses to run if the two disagree with this list).
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class ModelSpec:
    key: str  # metrics.json / loop_history.json key and the artefact's stem
    label: str  # human-readable name (report, plots)
    short: str  # legend label in the Figure 6 plot
    color: str  # plot and report colour
    artefact: str  # file written into run_dir by `crater-synth train`
    figure6: bool  # trained at every Figure 6 point (the paper plots LunarNet_ex and LunarSVM_ex)


REGISTRY: tuple[ModelSpec, ...] = (
    ModelSpec("lunarnet_ex", "LunarNet_ex", "Net", "#2563eb", "lunarnet_ex.pt", True),
    ModelSpec("lunarsvm_ex", "LunarSVM_ex", "SVM", "#16a34a", "lunarsvm_ex.joblib", True),
    ModelSpec("hog_svm", "HOG + linear SVM", "HOG", "#d97706", "hog_svm.joblib", False),
)
SPECS: dict[str, ModelSpec] = {s.key: s for s in REGISTRY}
MODELS: tuple[str, ...] = tuple(s.key for s in REGISTRY)
FIGURE6_MODELS: tuple[str, ...] = tuple(s.key for s in REGISTRY if s.figure6)
# The closed loop (paper Fig. 3) stops when this model's real accuracy reaches loop.threshold.
LOOP_MODEL = "lunarnet_ex"
ARTEFACTS: tuple[str, ...] = tuple(s.artefact for s in REGISTRY)


def label(key: str) -> str:
    """Human-readable name of a model key (the key itself for a model this version does not know)."""
    spec = SPECS.get(key)
    return spec.label if spec else key
