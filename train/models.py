"""The three classifiers of the paper (docs/classifiers.md).

- :class:`LunarNetEx` -- the shallow CNN of Fig. 5, layers in the paper's order:
  CONV1 (stride 1) -> ReLU1 -> POOL -> CONV2 -> ReLU2 -> FC1 -> ReLU3 -> FC2 -> Softmax.
  The softmax is applied by the loss (``CrossEntropyLoss``) in training and by :meth:`predict_proba`
  at inference, so ``forward`` returns logits.
- LunarSVM_ex -- a multiclass linear SVM (scikit-learn ``SGDClassifier(loss="hinge")``, one-vs-rest)
  on standardised FC1 activations (after ReLU3) of the trained LunarNet_ex.
- HOG + linear SVM baseline (``skimage.feature.hog`` + the same SGD linear SVM).
"""

from __future__ import annotations

from collections import OrderedDict

import numpy as np
import torch
from skimage.feature import hog
from sklearn.linear_model import SGDClassifier
from sklearn.pipeline import make_pipeline
from sklearn.preprocessing import StandardScaler
from torch import nn

from crater_core.settings import HogSettings, ModelSettings, SvmSettings

PAPER_LAYER_ORDER = ("conv1", "relu1", "pool", "conv2", "relu2", "flatten", "fc1", "relu3", "fc2")


def _geometry(model: ModelSettings) -> dict:
    """Layer sizes of LunarNet_ex from the (validated) ``model`` settings."""
    h1, hp, h2 = model.feature_sizes()
    c1, pool, c2 = model.conv1, model.pool, model.conv2
    return dict(
        n=model.input_size,
        c1=c1.channels,
        k1=c1.kernel,
        pk=pool.kernel,
        ps=pool.stride,
        c2=c2.channels,
        k2=c2.kernel,
        s2=c2.stride,
        f1=model.fc1,
        nc=model.num_classes,
        h1=h1,
        hp=hp,
        h2=h2,
    )


class LunarNetEx(nn.Module):
    """LunarNet_ex; input (B, 1, N, N) normalised crops, output (B, num_classes) logits."""

    def __init__(self, model: ModelSettings):
        super().__init__()
        g = _geometry(model)
        self.geometry = g
        dropout = model.dropout
        layers: list[tuple[str, nn.Module]] = [
            ("conv1", nn.Conv2d(1, g["c1"], g["k1"], stride=1)),
            ("relu1", nn.ReLU(inplace=True)),
            ("pool", nn.MaxPool2d(g["pk"], g["ps"])),
            ("conv2", nn.Conv2d(g["c1"], g["c2"], g["k2"], stride=g["s2"])),
            ("relu2", nn.ReLU(inplace=True)),  # no pooling after CONV2 (paper)
            ("flatten", nn.Flatten()),
            ("fc1", nn.Linear(g["c2"] * g["h2"] * g["h2"], g["f1"])),
            ("relu3", nn.ReLU(inplace=True)),
        ]
        if dropout > 0:
            layers.append(("drop3", nn.Dropout(dropout)))
        layers.append(("fc2", nn.Linear(g["f1"], g["nc"])))
        self.layers = nn.Sequential(OrderedDict(layers))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.layers(x)

    def fc1_features(self, x: torch.Tensor) -> torch.Tensor:
        """FC1 activations after ReLU3 (LunarSVM_ex's features)."""
        for name, layer in self.layers.named_children():
            x = layer(x)
            if name == "relu3":
                return x
        raise AssertionError("no relu3 layer")  # pragma: no cover

    @torch.no_grad()
    def predict_proba(self, x: torch.Tensor) -> torch.Tensor:
        """The Softmax layer of Fig. 5."""
        return torch.softmax(self.forward(x), dim=1)


def parameter_count(model: nn.Module) -> int:
    return int(sum(p.numel() for p in model.parameters()))


def multiply_adds(model: ModelSettings) -> dict:
    """Multiply-accumulate operations per image, by layer (FLOPs ~= 2 x MACs)."""
    g = _geometry(model)
    macs = {
        "conv1": g["h1"] ** 2 * g["c1"] * g["k1"] ** 2,
        "conv2": g["h2"] ** 2 * g["c2"] * g["c1"] * g["k2"] ** 2,
        "fc1": g["c2"] * g["h2"] ** 2 * g["f1"],
        "fc2": g["f1"] * g["nc"],
    }
    macs["total"] = sum(macs.values())
    return macs


# ------------------------------------------------------------------------------------------------
# Linear SVMs (scikit-learn)
# ------------------------------------------------------------------------------------------------
def make_linear_svm(svm: SvmSettings, seed: int):
    """Standardise -> multiclass (one-vs-rest) linear SVM trained by SGD on the hinge loss."""
    return make_pipeline(
        StandardScaler(),
        SGDClassifier(
            loss="hinge",
            alpha=svm.alpha,
            max_iter=svm.max_iter,
            tol=svm.tol,
            random_state=int(seed) & 0x7FFFFFFF,
        ),
    )


def hog_features(images: np.ndarray, hog_settings: HogSettings) -> np.ndarray:
    """HOG descriptors (skimage) of normalised (N, H, W) images -> (N, D) float32."""
    ppc = hog_settings.pixels_per_cell
    cpb = hog_settings.cells_per_block
    ori = hog_settings.orientations
    feats = [
        hog(
            im,
            orientations=ori,
            pixels_per_cell=(ppc, ppc),
            cells_per_block=(cpb, cpb),
            block_norm="L2-Hys",
            feature_vector=True,
        )
        for im in images
    ]
    return np.asarray(feats, dtype=np.float32)
