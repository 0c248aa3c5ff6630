"""Render sizes are bounded and the free-disk preflight estimates the EXRs the sweep will really write
(crater_core.settings.RenderSettings, crater_synth.dataset.disk); a real frame larger than navigate's
bound is refused from its header (train.realframes). Fast: no rendering, the free space is faked."""

from __future__ import annotations

import math
import re
import warnings

import numpy as np
import pytest

from crater_core.files import size_text
from crater_core.settings import MAX_ROI_MIN_PX
from crater_synth.config import ConfigError, load_settings
from crater_synth.dataset import build, disk
from crater_synth.dataset.build import build_dataset
from crater_synth.errors import UserError
from train import realframes
from train.errors import RealSetError

TB = 10**12


@pytest.mark.parametrize(
    "override, key",
    [
        ("render.roi_min_px=100000", "roi_min_px"),
        ("render.shadow_map_px=100000", "shadow_map_px"),
        ("render.shadow_map_levels=40", "shadow_map_levels"),
    ],
)
def test_huge_render_sizes_are_refused_naming_the_key(override, key):
    with pytest.raises(ConfigError) as info:
        load_settings([override])
    msg = str(info.value)
    assert key in msg and "\n" not in msg.strip()
    # the bound itself is accepted
    assert load_settings([f"render.roi_min_px={MAX_ROI_MIN_PX}"]).render.roi_min_px == MAX_ROI_MIN_PX


def test_one_exr_is_estimated_from_the_contract_channels():
    # 2 float32 (IF, depth) + 4 half (normals, lit) = 16 B per pixel, before compression
    assert disk.RAW_BYTES_PER_PX == 16
    assert disk.exr_bytes(100, 50, 1.0) == disk.EXR_HEADER_BYTES + 100 * 50 * 16
    assert disk.exr_bytes(100, 50) < disk.exr_bytes(100, 50, 1.0)


def test_a_huge_roi_sweep_is_refused_before_rendering_with_the_real_estimate(tmp_path, monkeypatch):
    s = load_settings(
        [
            "sweep=paper",
            f"render.roi_min_px={MAX_ROI_MIN_PX}",
            f"out_dir={tmp_path / 'ds'}",
            f"data_dir={tmp_path / 'data'}",
        ]
    )
    n = len(s.sweep.grid) * len(s.craters)
    # 1 TB free: room for the sweep at the old 600 kB per render, far from it at the real crop size
    assert n * 600_000 * 1.1 < TB
    monkeypatch.setattr(disk, "free_bytes", lambda path: TB)
    monkeypatch.setattr(build, "run_workers", lambda *a, **k: pytest.fail("rendered despite the full disk"))
    side = math.ceil(MAX_ROI_MIN_PX * max(s.sweep.grid.sigmas) / min(s.sweep.grid.sigmas))
    each = disk.exr_bytes(side, side)
    assert each > 100 * 600_000  # a 5,735 px crop: hundreds of MB, not 600 kB
    with pytest.raises(UserError) as info:
        build_dataset(s, progress=False, warn=None)
    msg = str(info.value)
    assert "\n" not in msg and "not enough free disk" in msg
    assert f"{n} renders need ~{size_text(int(n * each * 1.1))}" in msg
    assert f"~{size_text(each)} each" in msg and size_text(TB) in msg
    assert not (tmp_path / "ds").exists()  # refused before rendering: nothing left behind


def test_the_paper_sweep_fits_the_same_disk(tmp_path, monkeypatch):
    """The default roi (150 px): ~210 px crops, ~0.5 MB each, so 1 TB is room enough."""
    s = load_settings(["sweep=paper"])
    monkeypatch.setattr(disk, "free_bytes", lambda path: TB)
    n = len(s.sweep.grid) * len(s.craters)
    disk.check_sweep_disk(tmp_path, n, s.render, s.sweep.grid, [])
    side = disk.least_crop_side(s.render, s.sweep.grid)
    assert 200 <= side <= 215 and 300_000 < disk.exr_bytes(side, side) < 600_000


def _rows(tmp_path, sizes_and_shapes):
    rows = []
    for i, (size, (w, h)) in enumerate(sizes_and_shapes):
        rel = f"c/r{i}.exr"
        (tmp_path / "c").mkdir(exist_ok=True)
        (tmp_path / rel).write_bytes(b"\0" * size)
        rows.append({"path": rel, "width": w, "height": h})
    return rows


def test_a_resumed_dataset_uses_its_own_measured_compression(tmp_path, monkeypatch):
    raw = 100 * 100 * 16
    rows = _rows(tmp_path, [(disk.EXR_HEADER_BYTES + raw // 2, (100, 100)), (disk.EXR_HEADER_BYTES + raw, (100, 100))])
    rows.append({"path": "c/missing.exr", "width": 100, "height": 100})  # no file: not measured
    assert disk.measured_compression(rows, tmp_path) == pytest.approx(0.75, abs=1e-4)
    assert disk.measured_compression([], tmp_path) == disk.EXR_COMPRESSION
    # 1000 px crops at the measured 0.5 of raw: refused by a disk that would hold them at 0.25
    (tmp_path / "h").mkdir()
    half = _rows(tmp_path / "h", [(disk.EXR_HEADER_BYTES + raw // 2, (100, 100))])
    crops = [[0, 0, 1000, 1000]] * 10
    need = 10 * disk.exr_bytes(1000, 1000, 0.5)
    monkeypatch.setattr(disk, "free_bytes", lambda path: need)  # < need * 1.1
    with pytest.raises(UserError, match=f"10 renders need ~{re.escape(size_text(int(need * 1.1)))}"):
        disk.check_planned_disk(tmp_path / "h", crops, half)
    monkeypatch.setattr(disk, "free_bytes", lambda path: int(need * 1.2))
    disk.check_planned_disk(tmp_path / "h", crops, half)


def test_a_real_frame_over_the_bound_is_refused_from_its_header(tmp_path, monkeypatch):
    import rasterio
    from rasterio.transform import Affine

    path = tmp_path / "frame.tif"
    crs = "+proj=ortho +lat_0=-88.8 +lon_0=60 +x_0=0 +y_0=0 +R=1737400 +units=m +no_defs"
    profile = dict(driver="GTiff", width=40, height=30, count=1, dtype="float32", crs=crs)
    with (
        warnings.catch_warnings(),
        rasterio.open(path, "w", transform=Affine(100.0, 0.0, 0.0, 0.0, -100.0, 0.0), **profile) as ds,
    ):
        ds.write(np.ones((30, 40), np.float32), 1)
    assert realframes.open_frame(path).image.shape == (30, 40)
    monkeypatch.setattr(realframes, "MAX_FRAME_PIXELS", 40 * 30 - 1)
    with pytest.raises(RealSetError, match=r"is 40 x 30 px, more than the 1199 px read at once"):
        realframes.open_frame(path)
