"""The public Dataset API over ``crater-synth export`` directories (docs/export.md, "Loading an export in
PyTorch"): :class:`ParquetExport` (map-style), :class:`WebDatasetExport` (streaming, shards split across
DataLoader workers), :func:`open_export` (the one the export's format calls for), :func:`iter_records`
and :func:`read_index`.

The implementation lives in :mod:`train.exported` (train/ sits below crater_synth and the classifier's
own training reads exports through it, ``train.export_dir``); this module is the name to import::

    from torch.utils.data import DataLoader
    from crater_synth.data import open_export

    for images, labels in DataLoader(open_export("demo-parquet"), batch_size=32, num_workers=2):
        ...  # images: float32 (32, C, H, W); labels: {"crater": [...], "sun_elevation": tensor, ...}
"""

from __future__ import annotations

from train.exported import (
    ExportRecord,
    ParquetExport,
    WebDatasetExport,
    iter_records,
    open_export,
    read_index,
)

__all__ = ["ExportRecord", "ParquetExport", "WebDatasetExport", "iter_records", "open_export", "read_index"]
