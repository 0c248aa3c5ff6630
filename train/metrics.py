"""Classification metrics: thin wrappers around ``sklearn.metrics`` with the project's conventions
(class order = ``class_names``; NaN instead of an exception when there is nothing to measure)."""

from __future__ import annotations

import warnings

import numpy as np
from sklearn.metrics import accuracy_score, balanced_accuracy_score, confusion_matrix


def class_mean_accuracy(y_true: np.ndarray, y_pred: np.ndarray) -> float:
    """Mean over the classes present in ``y_true`` of the per-class accuracy (recall): the paper's
    "mean accuracy" (``sklearn.metrics.balanced_accuracy_score``). NaN for an empty set."""
    y_true, y_pred = np.asarray(y_true), np.asarray(y_pred)
    if y_true.size == 0:
        return float("nan")
    with warnings.catch_warnings():  # a predicted class absent from y_true is fine: it only costs recall
        warnings.filterwarnings("ignore", message="y_pred contains classes not in y_true")
        return float(balanced_accuracy_score(y_true, y_pred))


def accuracy(y_true: np.ndarray, y_pred: np.ndarray) -> float:
    """Fraction of correct predictions; NaN for an empty set."""
    y_true = np.asarray(y_true)
    return float(accuracy_score(y_true, np.asarray(y_pred))) if y_true.size else float("nan")


def confusion(y_true: np.ndarray, y_pred: np.ndarray, n_classes: int) -> list[list[int]]:
    """n x n counts; rows: true class, columns: predicted class (class order of ``class_names``)."""
    m = confusion_matrix(np.asarray(y_true), np.asarray(y_pred), labels=np.arange(n_classes))
    return m.astype(int).tolist()
