"""The training loop every detector shares (torchvision's references/detection shape): the draw
probabilities of several training sources, seeds, AdamW with a one-cycle schedule, the network's memory
layout and the precision of its forward pass. :mod:`train.crater_detector` (the learned detector) and
:mod:`train.fcos_detector` (FCOS) each give it their model and their step's loss. torch and core only."""

from __future__ import annotations

import time

import numpy as np
import torch
from torch import nn

from crater_core.settings_nav import DetectorTrainSettings
from train.model_files import DetectorModelError


def source_probabilities(source, shares) -> np.ndarray | None:
    """Draw probability of each sample so that source k (``source``: the source index of each sample) makes
    ``shares[k]`` of the draws, evenly among its samples; None (uniform over samples) when ``shares`` is
    empty. Without it a small source (240 survey frames beside 2,000 procedural ones) would barely be seen."""
    if not shares:
        return None
    source = np.asarray(source, int)
    n_sources = int(source.max()) + 1
    if len(shares) != n_sources:
        raise DetectorModelError(f"source_shares has {len(shares)} entries for {n_sources} training sources")
    counts = np.bincount(source, minlength=n_sources)
    w = np.asarray(shares, float) / max(float(np.sum(shares)), 1e-300)
    p = w[source] / counts[source]
    return p / p.sum()


def fit(
    build,
    samples: list,
    settings: DetectorTrainSettings,
    step_loss,
    log=None,
    device: str = "cpu",
    source=None,
    channels_last: bool = False,
):
    """The training loop of every detector (torchvision's references/detection shape): seeds, the draw
    probabilities of ``source`` (:func:`source_probabilities`), ``build()`` the model, AdamW with a one-cycle
    schedule, and per step ``step_loss(forward, rng, p, gen)`` -> (loss, {part: value}), ``forward`` the model's
    forward pass at ``settings.precision`` (:func:`autocast_forward`), the model laid out channels last when
    ``channels_last`` (the CenterNet network's choice, ``settings.channels_last``). Returns {"model" (on the
    CPU, standard layout), "history", "seconds", "checkpoints"} (step -> state dict copies at
    ``settings.checkpoints``)."""
    if not samples:
        raise DetectorModelError("no training frames: render some with `crater-synth nav-detector-frames`")
    torch.manual_seed(settings.seed)
    if settings.threads:
        torch.set_num_threads(settings.threads)
    rng = np.random.default_rng(settings.seed)
    p = source_probabilities(np.zeros(len(samples), int) if source is None else source, settings.source_shares)
    gen = torch.Generator(device=device)
    gen.manual_seed(settings.seed)
    model = build().to(device, memory_format=torch.channels_last if channels_last else torch.contiguous_format)
    forward = autocast_forward(model, settings.precision, device)
    opt = torch.optim.AdamW(model.parameters(), lr=settings.lr, weight_decay=settings.weight_decay)
    sched = torch.optim.lr_scheduler.OneCycleLR(opt, max_lr=settings.lr, total_steps=settings.steps, pct_start=0.1)
    history, checkpoints = [], {}
    t0 = time.perf_counter()
    model.train()
    for step in range(1, settings.steps + 1):
        loss, parts = step_loss(forward, rng, p, gen)
        opt.zero_grad()
        loss.backward()
        opt.step()
        sched.step()
        if step % 50 == 0 or step == settings.steps:
            row = {k: round(float(v), 4) for k, v in parts.items()}
            history.append({"step": step, "loss": round(float(loss.detach()), 4), **row})
            if log:
                log(
                    f"step {step}/{settings.steps}: loss {float(loss.detach()):.3f} "
                    + ", ".join(f"{k} {v}" for k, v in row.items())
                )
        if step in settings.checkpoints:
            checkpoints[step] = {k: v.detach().cpu().clone() for k, v in model.state_dict().items()}
    model.eval()
    # handed back in the standard layout, as every model built here starts (files are written in it anyway)
    model = model.cpu().to(memory_format=torch.contiguous_format)
    return {"model": model, "history": history, "seconds": time.perf_counter() - t0, "checkpoints": checkpoints}


def autocast_forward(model: nn.Module, precision: str, device: str):
    """What a training step calls for the forward pass: ``model`` itself at "fp32"; at "bf16" the same call
    under ``torch.autocast`` in bfloat16 (convolutions and matrix products; the weights, their gradients and
    the optimiser stay float32, as torchvision's references train under autocast), its tensor outputs (a
    tensor, or a dict of losses) handed back in float32. The CenterNet network's loss is then computed in
    float32 outside the forward pass; FCOS computes its losses inside it, under autocast, as torchvision's
    references do."""
    if precision == "fp32":
        return model
    device_type = torch.device(device).type

    def forward(*args, **kwargs):
        with torch.autocast(device_type, dtype=torch.bfloat16):
            out = model(*args, **kwargs)
        if isinstance(out, dict):
            return {k: v.float() for k, v in out.items()}
        return out.float()

    return forward
