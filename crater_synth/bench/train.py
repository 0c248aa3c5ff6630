"""Training benchmark for `make bench` (``crater-synth bench --part train``): throughput and time to
reach the validation target. Orchestration over ``train/``, so it lives in the host layer."""

from __future__ import annotations

import os
import resource
import time

from crater_core.settings import ModelSettings, Settings


def model_throughput(
    model_settings: ModelSettings, batch_size: int = 64, steps: int = 10, device: str = "cpu"
) -> float:
    """Forward+backward+Adam images/s of LunarNet_ex alone on random input (no data loading)."""
    import torch

    from train.models import LunarNetEx

    model = LunarNetEx(model_settings).to(device)
    opt = torch.optim.Adam(model.parameters(), 1e-3)
    n = model_settings.input_size
    x = torch.rand(batch_size, 1, n, n, device=device)
    y = torch.randint(0, model_settings.num_classes, (batch_size,), device=device)
    loss_fn = torch.nn.CrossEntropyLoss()
    for i in range(steps + 2):  # two warm-up steps
        if i == 2:
            if device == "cuda":
                torch.cuda.synchronize()
            t0 = time.perf_counter()
        opt.zero_grad()
        loss_fn(model(x), y).backward()
        opt.step()
    if device == "cuda":
        torch.cuda.synchronize()
    return steps * batch_size / (time.perf_counter() - t0)


def run_train_bench(settings: Settings) -> dict:
    """Train LunarNet_ex on the manifest at ``train.dataset_dir`` (config as given: ``max_epochs``,
    ``target_val_accuracy``, threads, ...) and report:

    - ``train_images_per_s``: training images/s of the full loop (cached crops -> sensor model ->
      normalisation -> forward/backward/Adam), averaged over all epochs;
    - ``model_images_per_s``: the same for the network alone on random input (the loop's upper bound);
    - ``time_to_target_s``: wall time from the start of training to the end of the epoch whose
      class-mean validation accuracy first reached the target (``None`` if it never did);
    - cache build time (first run decodes the EXRs; later runs reuse the cache), its size on disk;
    - peak RSS of this process and of the cache-build workers.
    Nothing is written except the crop cache (no run_dir artefacts)."""
    import torch

    from train.data import build_datasets
    from train.models import multiply_adds
    from train.trainer import configure_torch, model_for, train_lunarnet

    device = configure_torch(settings.train)
    t0 = time.perf_counter()
    data = build_datasets(settings, progress=False)
    data_s = time.perf_counter() - t0
    _, summary = train_lunarnet(data, settings, run_dir=None, progress=settings.train.progress)
    arch = model_for(settings.model, data.class_names)
    return {
        "dataset_dir": settings.train.dataset_dir,
        "train_images": len(data.train),
        "val_images": len(data.val),
        "data_setup_s": round(data_s, 3),
        "cache_built": bool(data.info.get("cache_built")),
        "cache_seconds": data.info.get("cache_seconds"),
        "epochs": len(summary["history"]),
        "train_images_per_s": round(summary["train_images_per_s"], 2),
        "model_images_per_s": round(model_throughput(arch, settings.train.batch_size, 5, device.type), 2),
        "time_to_target_s": None if summary["time_to_target_s"] is None else round(summary["time_to_target_s"], 3),
        "reached_target": summary["reached_target"],
        "target_val_accuracy": summary["target_val_accuracy"],
        "val_accuracy": summary["val_accuracy"],
        "train_seconds": round(summary["train_seconds"], 3),
        "device": summary["device"],
        "torch_threads": torch.get_num_threads(),
        "cpu_count": os.cpu_count(),
        "parameters": summary["parameters"],
        "multiply_adds_per_image": multiply_adds(arch)["total"],
        # ru_maxrss is in KiB on Linux. The crops stream from the memmap cache, so the training
        # process stays bounded whatever the sweep's size; children = the largest cache-build worker.
        "peak_rss_mb": {
            "process": round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, 1),
            "cache_worker": round(resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024, 1),
        },
        "cache_bytes": data.info.get("cache_bytes"),
    }
