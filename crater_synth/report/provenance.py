"""Section 9 (provenance of every data product, the dataset and the run) and the test-set limit that the
header and section 9 state."""

from __future__ import annotations

from pathlib import Path
from typing import Mapping

from crater_core import schema
from crater_synth.report.context import Ctx, not_run
from crater_synth.report.inputs import RUN_CONFIG_FILE, SUMMARY_FILE, config_craters, load_summary
from data_manifest import products as P


def _product_rows(cfg: Mapping) -> list[dict]:
    out = []
    data_dir = Path(str(cfg.get("data_dir") or "data"))
    for pid, p in P.load_products().items():
        if p["source"] == "embedded":
            pinned = p["sha256"]
            try:
                path = P.embedded_path(pid)
                actual = P.cached_sha256(path)
                status = (
                    "embedded, sha256 verified" if actual == pinned else f"embedded, sha256 MISMATCH ({actual[:12]}…)"
                )
                cls = "ok" if actual == pinned else "bad"
            except P.ProductError as exc:
                path, status, cls = p["package_path"], f"missing: {exc}", "bad"
            where = f"{p['package']} {p['package_version']}: {path}"
        else:
            files = p.get("files") or []
            pinned = ", ".join(f["sha256"] for f in files if f.get("sha256")) or "not pinned"
            base = P.products_dir(data_dir)
            have = [f for f in files if (base / f["name"]).is_file()]
            if not files:
                status, cls = "missing (no file pinned yet)", "na"
            elif len(have) == len(files):
                status, cls = "downloaded (present)", "ok"
            else:
                status, cls = f"missing ({len(have)}/{len(files)} files; crater-synth fetch-data {pid})", "na"
            where = str(base / (p.get("open") or "")) if files else "–"
        out.append(
            {
                "id": pid,
                "title": p.get("title", ""),
                "source": p["source"],
                "where": where,
                "sha256": pinned,
                "licence": p.get("licence", "–"),
                "status": status,
                "cls": cls,
            }
        )
    return out


def limits_text(ctx: Ctx) -> str:
    """The limit of the test set, stated in the header and in section 9."""
    from train.realset import LIMITS_NOTE

    rs = ctx.rc.cfg.get("realset") or {}
    m = ctx.metrics or {}
    per = m.get("test_per_crater") or {}
    n = max(per.values()) if per else rs.get("per_crater", 300)
    embedded = rs.get("include_embedded", True)
    run_note = m.get("limits")
    if m and "one real observation per crater" not in str(run_note or "").lower():
        embedded = False  # the run tested on labels-file frames only
    if not embedded:
        return str(run_note or LIMITS_NOTE)
    text = (
        f"The embedded real test set is ONE real LROC WAC observation per crater, seen {n} ways (σ, slewing "
        f"offsets and rotations of the same mosaic pixels, {rs.get('source_product', 'lroc_wac_south')}). Crops "
        "of the same crater are strongly correlated: the accuracies measure recognition of that single "
        "observation, not generalisation over real illumination conditions, and per-crater results tend to be "
        "all-or-nothing."
    )
    if rs.get("labels_file"):
        text += f" Frames from the labels file {rs['labels_file']} are tested as well."
    return text


def provenance(ctx: Ctx) -> dict:
    out: dict = {"products": _product_rows(ctx.rc.cfg)}
    ds = ctx.rc.dataset_dir
    if ctx.all_rows is None:
        out["dataset_not_run"] = not_run(f"no rendered dataset at {ds or 'train.dataset_dir (unset)'}", "dataset")
    else:
        rows = ctx.all_rows
        used = ctx.rows or []
        per = {c: sum(r["crater"] == c for r in rows) for c in dict.fromkeys(r["crater"] for r in rows)}
        axes = {
            k: sorted({round(float(r[k]), 4) for r in rows})
            for k in ("sun_elevation", "sun_azimuth", "cam_elevation", "cam_azimuth")
        }
        sigmas = sorted({k for r in rows for k in r["sigma_boxes"]}, key=float)
        facts = [
            ("dataset directory", str(ds)),
            ("chosen from", ctx.rc.dataset_dir_source),
            ("manifest", f"{ds / schema.MANIFEST_NAME} (sha256 {schema.sha256_file(ds / schema.MANIFEST_NAME)})"),
            ("manifest rows", f"{len(rows):,}"),
            (
                "rows the run trained on",
                f"{len(used):,} (train.select: a subset of the sweep grid, as in the "
                "closed loop and the Figure 6 experiments; sections 1–3 show this subset)"
                if len(used) != len(rows)
                else "all",
            ),
            ("rows per crater", ", ".join(f"{c}: {n:,}" for c, n in per.items())),
            ("code_version", ", ".join(sorted({r["code_version"] for r in rows}))),
            ("renderer", ", ".join(sorted({r["renderer"] for r in rows}))),
            ("terrain_ids", ", ".join(sorted({r["terrain_id"] for r in rows}))),
            ("render digests", ", ".join(sorted({r["render_digest"] for r in rows}))),
            ("schema_version", ", ".join(str(v) for v in sorted({r["schema_version"] for r in rows}))),
            ("ROI σ boxes", ", ".join(sigmas)),
        ]
        for k, v in axes.items():
            shown = ", ".join(f"{x:g}" for x in v[:12]) + (" …" if len(v) > 12 else "")
            facts.append((f"{k.replace('_', ' ')} ({len(v)} values, °)", shown))
        out["dataset"] = facts
    cfg = ctx.rc.cfg
    facts = [
        ("run directory", str(ctx.run_dir.resolve())),
        (
            "configuration",
            f"{ctx.run_dir / RUN_CONFIG_FILE}"
            if ctx.rc.saved
            else "composed defaults + command-line overrides (the run saved no config.yaml)",
        ),
        ("sweep", str((cfg.get("sweep") or {}).get("name", "–"))),
        ("seed", str(cfg.get("seed", "–"))),
        ("craters", ", ".join(c["name"] for c in config_craters(cfg))),
    ]
    summ = load_summary(ctx.run_dir / SUMMARY_FILE)
    if summ is not None:
        info = summ.get("data") or {}
        facts += [
            ("training / validation images", f"{summ.get('train_images', '–')} / {summ.get('val_images', '–')}"),
            (
                "validation split",
                f"by {info.get('split_by', '–')}, "
                f"{info.get('val_groups') and len(info['val_groups'])} "
                f"of {info.get('groups', '–')} groups held out",
            ),
            ("training σ", ", ".join(str(s) for s in info.get("sigmas") or []) or "–"),
        ]
    rs = cfg.get("realset") or {}
    facts += [
        (
            "real test set",
            f"{rs.get('source_product', '–')}: {rs.get('per_crater', '–')} crops per crater, "
            f"σ {rs.get('sigmas', '–')}, offsets ±{rs.get('max_offset_frac', '–')} × side, "
            f"rotations ±{rs.get('max_rotation_deg', '–')}°, seed {rs.get('seed', '–')}"
            + (f"; labels file {rs['labels_file']}" if rs.get("labels_file") else ""),
        )
    ]
    out["run"] = facts
    out["limits"] = limits_text(ctx)
    return out
