"""torchvision on a CPU torch whose build of torchvision's compiled ops does not load.

PyPI's Linux ``torchvision`` wheel is built against PyPI's CUDA torch: beside the CPU torch of ``make setup``
its ``_C.so`` (which needs ``libtorch_cuda``) does not load, and ``import torchvision`` then fails inside
``torchvision._meta_registrations``, which registers fake kernels for the operators ``torchvision::nms``
and ``torchvision::qnms`` whether or not they exist. The detectors here need one compiled op only, NMS, so
:func:`import_torchvision` defines those two schemas with ``torch.library`` and a pure-torch kernel before
importing torchvision. Where the compiled ops load (PyTorch's CPU index build, or a matching CUDA pair)
they are used untouched.
"""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import torch

_SCHEMA = "(Tensor dets, Tensor scores, float iou_threshold) -> Tensor"
_state: dict = {}


def greedy_nms(dets: torch.Tensor, scores: torch.Tensor, iou_threshold: float) -> torch.Tensor:
    """Indices of the boxes (x1, y1, x2, y2) kept by greedy NMS, in decreasing score order (ties: the lower
    index first, a stable sort as torchvision's CPU kernel): a box is dropped when its IoU with a kept,
    higher-ranked box exceeds ``iou_threshold``. The pairwise IoU is one tensor operation; the loop runs
    once per kept box."""
    n = int(dets.shape[0])
    if n == 0:
        return torch.empty(0, dtype=torch.long, device=dets.device)
    order = torch.sort(scores, descending=True, stable=True)[1]
    b = dets[order].to(torch.float64)
    area = (b[:, 2] - b[:, 0]) * (b[:, 3] - b[:, 1])
    wh = (torch.minimum(b[:, None, 2:], b[None, :, 2:]) - torch.maximum(b[:, None, :2], b[None, :, :2])).clamp(min=0)
    inter = wh[..., 0] * wh[..., 1]
    # A NaN IoU (two empty boxes) compares False, as in the C++ kernel: neither suppresses the other.
    over = (inter / (area[:, None] + area[None, :] - inter)) > iou_threshold
    alive = torch.ones(n, dtype=torch.bool, device=dets.device)
    keep = []
    i = 0
    while i < n:
        keep.append(i)
        alive &= ~over[i]
        alive[: i + 1] = False
        rest = torch.nonzero(alive)
        if rest.numel() == 0:
            break
        i = int(rest[0, 0])
    return order[torch.tensor(keep, dtype=torch.long, device=dets.device)]


def _qnms(dets: torch.Tensor, scores: torch.Tensor, iou_threshold: float) -> torch.Tensor:
    # torchvision passes the integer representations of quantized boxes and scores.
    return greedy_nms(dets.to(torch.float64), scores.to(torch.float64), iou_threshold)


def _compiled_ops_load(package_dir: Path) -> bool:
    lib = next(iter(sorted(package_dir.glob("_C*.so")) + sorted(package_dir.glob("_C*.pyd"))), None)
    if lib is None:
        return False
    try:
        torch.ops.load_library(str(lib))
    except (OSError, RuntimeError):
        return False
    return True


def _define_ops() -> None:
    """``torchvision::nms`` and ``torchvision::qnms`` with :func:`greedy_nms` as their CPU and CUDA kernel
    (the Library objects are kept: dropping one deregisters its operators)."""
    if hasattr(torch.ops.torchvision, "nms"):
        return
    lib = torch.library.Library("torchvision", "DEF")
    impl = torch.library.Library("torchvision", "IMPL")
    for name, kernel in (("nms", greedy_nms), ("qnms", _qnms)):
        lib.define(name + _SCHEMA)
        for key in ("CPU", "CUDA"):
            impl.impl(name, kernel, key)
    _state["libraries"] = (lib, impl)


def import_torchvision():
    """The ``torchvision`` module, with ``torchvision.ops.nms`` usable: its own compiled ops when they load,
    else :func:`greedy_nms` (see the module's docstring). Raises ImportError when torchvision is not installed."""
    if "torchvision" in sys.modules and "torchvision_fallback" not in _state:
        return sys.modules["torchvision"]
    spec = importlib.util.find_spec("torchvision")
    if spec is None or spec.origin is None:
        raise ImportError("torchvision is not installed")
    fallback = _state.setdefault("torchvision_fallback", not _compiled_ops_load(Path(spec.origin).parent))
    if fallback:
        _define_ops()
    import torchvision
    import torchvision.ops.boxes

    if fallback:
        # torchvision.ops.nms first asserts that the compiled library loaded; our schemas stand in for it,
        # and this name (bound in ops.boxes only) is that assertion's one use on the NMS path. Other
        # compiled ops (roi_align, deform_conv2d ...) stay missing and fail with torch's own error.
        torchvision.ops.boxes._assert_has_ops = lambda: None
    return torchvision


def uses_fallback_nms() -> bool:
    """Whether :func:`import_torchvision` stood in for torchvision's compiled NMS."""
    return bool(_state.get("torchvision_fallback"))
