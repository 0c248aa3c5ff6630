"""Extract the polar subset of the LU1319381 lunar crater catalogue that the landmark maps are checked against.

The catalogue (Wang et al. 2021; Wu et al. 2022, docs in data_manifest/catalogues/lu1319381_polar/README.md)
circulates as dBase tables of 30 x 30 degree tiles (``HKPolyU_<lon>_<lat>.dbf``: ID, Longitude, Latitude,
Diameter_m, Depth_m, Source, ...). This tool reads the tiles poleward of 60 degrees and writes the craters of
D >= 8 km as one CSV (id, lon, lat, diameter_km, depth_m, source), sorted by id, atomically::

    python -m crater_synth.tools.lu_catalogue TILE_DIR OUT.csv [--min-diameter-km 8] [--min-abs-lat 60]

8 km, not 10: a landmark of 10 km matches a listed crater down to 8 km (diameters within 25 %). The
finer list for the maps of finer DEM layers near the poles: ``--min-diameter-km 1 --min-abs-lat 88``.
"""

from __future__ import annotations

import argparse
import csv
import io
import struct
import sys
from pathlib import Path

from crater_core.schema import atomic_write_text

MIN_DIAMETER_KM = 8.0
MIN_ABS_LAT_DEG = 60.0
COLUMNS = ("id", "lon", "lat", "diameter_km", "depth_m", "source")


def read_dbf(path: Path) -> list[dict]:
    """Rows of a dBase III table (numeric fields as float, others as stripped text); one error naming
    the file when it is not one."""
    data = path.read_bytes()
    try:
        n_rows, header_len, row_len = struct.unpack("<IHH", data[4:12])
        fields, off = [], 32
        while data[off] != 0x0D:
            name = data[off : off + 11].split(b"\0")[0].decode("ascii")
            fields.append((name, chr(data[off + 11]), data[off + 16]))
            off += 32
        rows = []
        for i in range(n_rows):
            raw, pos, row = data[header_len + i * row_len : header_len + (i + 1) * row_len], 1, {}
            for name, kind, width in fields:
                text = raw[pos : pos + width].decode("latin-1").strip()
                pos += width
                row[name] = float(text) if kind in "NF" and text else text
            rows.append(row)
    except (IndexError, struct.error, UnicodeDecodeError, ValueError) as exc:
        raise SystemExit(f"{path}: not a readable dBase table ({exc})") from None
    return rows


def polar_subset(
    tiles: list[Path], min_diameter_km: float = MIN_DIAMETER_KM, min_abs_lat: float = MIN_ABS_LAT_DEG
) -> list[tuple]:
    """(id, lon, lat, diameter_km, depth_m, source) of every crater >= ``min_diameter_km`` poleward of
    ``min_abs_lat`` degrees."""
    out = {}
    for tile in tiles:
        for r in read_dbf(tile):
            d_km = r["Diameter_m"] / 1000.0
            if d_km >= min_diameter_km and abs(r["Latitude"]) >= min_abs_lat:
                key = int(r["ID"])
                out[key] = (
                    key,
                    round(r["Longitude"], 4),
                    round(r["Latitude"], 4),
                    round(d_km, 3),
                    round(r["Depth_m"], 1),
                    int(r["Source"]),
                )
    return [out[k] for k in sorted(out)]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("tile_dir", type=Path)
    ap.add_argument("out", type=Path)
    ap.add_argument("--min-diameter-km", type=float, default=MIN_DIAMETER_KM)
    ap.add_argument("--min-abs-lat", type=float, default=MIN_ABS_LAT_DEG)
    args = ap.parse_args(argv)
    tiles = sorted(args.tile_dir.glob("HKPolyU_*60-90[NS].dbf"))
    if not tiles:
        raise SystemExit(f"{args.tile_dir}: no HKPolyU_*60-90N/S.dbf tile")
    rows = polar_subset(tiles, args.min_diameter_km, args.min_abs_lat)
    buf = io.StringIO()
    writer = csv.writer(buf, lineterminator="\n")
    writer.writerow(COLUMNS)
    writer.writerows(rows)
    atomic_write_text(args.out, buf.getvalue())
    print(f"wrote {args.out}: {len(rows)} craters >= {args.min_diameter_km:g} km from {len(tiles)} tiles")
    return 0


if __name__ == "__main__":
    sys.exit(main())
