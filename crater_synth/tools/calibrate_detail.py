"""``python -m crater_synth.tools.calibrate_detail``: compare the DEM plus sub-DEM detail with a real LOLA
200 m crop, optionally fit the detail parameters and write hillshades (docs/detail.md), with
:mod:`crater_synth.tools.detail_calibration`.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from crater_core.errors import ContractError
from crater_synth.errors import UserError
from crater_synth.terrain.detail import DetailSettings, synthesize_detail
from crater_synth.tools.detail_calibration import (
    DEFAULT_DATA_DIR,
    OLD_SETTINGS_KW,
    REAL_CROP_PRODUCT,
    REAL_CROP_SPACING_M,
    TRANSFER_KEYS,
    comparison_rows,
    fit_parameters,
    grid_transfer_rows,
    load_real_crop,
    markdown_table,
    measure_real,
    population_summary,
    write_hillshades,
)


def main(argv=None) -> int:

    ap = argparse.ArgumentParser(
        prog="python -m crater_synth.tools.calibrate_detail",
        description="Compare LDEM + sub-DEM detail with a real LOLA 200 m crop.",
    )
    ap.add_argument(
        "--dem",
        default=REAL_CROP_PRODUCT,
        help="the real crop: a registered DEM product id or a georeferenced DEM file with 200 m "
        f"pixels and heights above the sphere (default {REAL_CROP_PRODUCT})",
    )
    ap.add_argument("--data-dir", default=DEFAULT_DATA_DIR, help="where downloaded products live (default data)")
    ap.add_argument("--out", help="folder for the hillshade PNGs (none written when omitted)")
    ap.add_argument("--seeds", type=int, default=4, help="detail draws averaged per model (default 4)")
    ap.add_argument("--fit", action="store_true", help="also run the parameter grid search (FIT_GRID)")
    ap.add_argument("--json", action="store_true", help="print JSON instead of markdown")
    a = ap.parse_args(argv)
    if a.seeds < 1:
        print(f"error: --seeds={a.seeds} must be >= 1", file=sys.stderr)
        return 2
    try:
        m = measure_real(load_real_crop(a.dem, a.data_dir), a.data_dir)
        rows = comparison_rows(m, seeds=range(a.seeds))
        fit = fit_parameters(m, seeds=range(a.seeds)) if a.fit else []
        transfer = grid_transfer_rows(m, seeds=range(a.seeds))
        population = {
            "old detail": population_summary(DetailSettings(**OLD_SETTINGS_KW)),
            "new detail": population_summary(DetailSettings()),
        }
    except (UserError, ContractError) as exc:
        print(f"error: {str(exc).splitlines()[0]}", file=sys.stderr)
        return 2
    head = {
        "crop": m["crop"],
        "top_left_xy_m": [round(v, 1) for v in m["top_left_xy_m"]],
        "residual_rms_m": m["residual_rms_m"],
        "background_fraction": float(m["mask"].mean()),
        "band_fraction": float(m["band_mask"].mean()),
    }
    if a.json:
        print(
            json.dumps(
                {
                    **head,
                    "rows": rows,
                    "grid_transfer": transfer,
                    "population": population,
                    "fit": [{"misfit": e, **kw} for e, kw in fit],
                },
                indent=1,
            )
        )
    else:
        print(json.dumps(head))
        print(markdown_table(rows))
        for grid, row in transfer.items():
            print(f"\nsub-DEM band on a {grid} grid")
            print(markdown_table(row, TRANSFER_KEYS))
        print("\ndrawn crater population, 400 m - 3.2 km, 10,000 km^2 (level ground for the shadows)")
        print(markdown_table(population))
        for e, kw in fit:
            print(f"misfit {e:.4f}  {kw}")
    if a.out:
        fields = {"real": m["real"], "ldem": m["ldem"]}
        for name, settings in (("old", DetailSettings(**OLD_SETTINGS_KW)), ("new", DetailSettings())):
            field, _ = synthesize_detail(m["ldem"].shape, REAL_CROP_SPACING_M, 1600.0, settings, key="calibration")
            fields[name] = m["ldem"] + field
        try:
            for p in write_hillshades(fields, Path(a.out)):
                print(p)
        except OSError as exc:
            print(f"error: cannot write hillshades to --out {a.out}: {exc.strerror or exc}", file=sys.stderr)
            return 2
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
