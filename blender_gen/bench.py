"""Renderer benchmark and fast-vs-direct comparison on a synthetic crater (docs/renderer.md).

    python -m blender_gen.bench --mode fast --suns 2 --cams 150 --workers 2
    python -m blender_gen.bench --mode both --suns 2 --cams 5 --workers 2     # + per-pixel comparison

Writes a Shackleton-sized synthetic terrain (bowl crater D = 21 km with undulations, near field
512^2 vertices over +-2.5 D, far field to +-300 km at 2 km, Moon curvature included) and jobs laid
out like the host's (paper-grid angles, ROI crops of ~210 px, sun-major), runs ``workers`` worker
processes (one thread each) on contiguous blocks, and prints one JSON summary: wall-clock
renders/s, the per-stage times the workers report (STATS lines), and the paper-sweep throughput
they imply (each lit map shared by 150 cameras, each G-buffer by the sun directions of a block).
Imports numpy and this package only (bpy runs in the worker subprocesses).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from crater_core import geometry

REPO = Path(__file__).resolve().parent.parent
HAPKE = {"w": 0.32, "xi": -0.25, "b0": 1.0, "h": 0.06, "theta_bar_deg": 23.657}


def bowl_crater_z(diameter_m: float):
    """Height function z(x, y) of a bowl crater (depth 0.2 D, raised rim 0.04 D; Pike 1977 fresh simple
    crater proportions) with gentle undulations: a stand-in for a DEM in benchmarks and tests."""
    radius = diameter_m / 2.0

    def z(x, y):
        r = np.hypot(x, y) / radius
        bowl = np.where(r < 1.0, 0.2 * diameter_m * (r**2 - 1.0) + 0.04 * diameter_m,
                        0.04 * diameter_m * np.exp(-3.0 * (r - 1.0)))
        return bowl + 0.003 * diameter_m * np.sin(x / (0.033 * diameter_m)) * np.cos(y / (0.043 * diameter_m))

    return z


def synthetic_terrain(path: Path, diameter_m: float = 21_000.0, near_n: int = 512, near_factor: float = 2.5,
                      far_half_m: float = 300_000.0, far_spacing_m: float = 2_000.0) -> dict:
    crater = bowl_crater_z(diameter_m)

    def grid(half, n, zf):
        xs = np.linspace(-half, half, n)
        x, y = np.meshgrid(xs, xs[::-1])
        z = zf(x, y) - geometry.curvature_drop_m(np.minimum(np.hypot(x, y), 0.99 * geometry.MOON_RADIUS_M))
        return np.stack([x, y, z], -1).astype(np.float32)

    near_half = near_factor * diameter_m
    near = grid(near_half, near_n, crater)
    far_n = int(round(2 * far_half_m / far_spacing_m)) + 1
    far = grid(far_half_m, far_n, lambda x, y: 1500.0 * np.sin(x / 40e3) * np.cos(y / 55e3))
    cx = 0.5 * (far[:-1, :-1, 0] + far[1:, 1:, 0])
    cy = 0.5 * (far[:-1, :-1, 1] + far[1:, 1:, 1])
    keep = ~((np.abs(cx) < near_half) & (np.abs(cy) < near_half))
    np.savez(path, near_xyz=near, far_xyz=far, far_keep_quads=keep)
    return {"terrain_id": f"bench-{near_n}", "rim_z_m": 0.04 * diameter_m}


def paper_items(diameter_m: float, rim_z: float, n_suns: int, n_cams: int, roi_min_px: int = 150,
                sigmas=(1.0, 1.2, 1.4), sun_stride: int = 1, cam_stride: int = 1) -> list[dict]:
    """Sun-major items on the paper grid: suns (0.16 k deg, 24 j deg), cameras (90 - 4 k, 24 j);
    every ``stride``-th grid point (a stride of 13 walks through elevations and azimuths)."""
    suns = [(0.16 * (1 + k % 10), 24.0 * (k // 10 % 15)) for k in range(0, n_suns * sun_stride, sun_stride)]
    cams = [(90.0 - 4.0 * (k % 10), 24.0 * (k // 10 % 15)) for k in range(0, n_cams * cam_stride, cam_stride)]
    rim = np.array([0.0, 0.0, rim_z])
    items = []
    for se, sa in suns:
        for ce, ca in cams:
            rng = 1.5 * diameter_m
            pose = geometry.look_at_camera(ce, ca, rng, 90.0)
            width = geometry.frame_width_for_roi(pose, rim, diameter_m / 2, roi_min_px, min(sigmas))
            ell = geometry.project_horizontal_circle(rim, diameter_m / 2, pose, width)
            (cu, cv), _ = geometry.project_points(rim, pose, width)
            b = geometry.roi_box((cu, cv), 2 * ell.a, max(sigmas))
            crop = [int(math.floor(b[0])), int(math.floor(b[1])), int(math.ceil(b[2])), int(math.ceil(b[3]))]
            i = len(items)
            items.append({"index": i, "indices": [0, 0, 0, 0], "sun_elevation": se, "sun_azimuth": sa,
                          "cam_elevation": ce, "cam_azimuth": ca, "range_m": rng, "fov_deg": 90.0,
                          "frame_width": width, "crop": crop, "rel_path": f"bench/{i:06d}.exr", "header": {}})
    return items


def run_block(job: dict, job_file: Path) -> subprocess.Popen:
    """Start a worker; its stdout/stderr go to files next to the job (a pipe read only after
    another worker finished would block this one's RESULT writes and distort the timing)."""
    job_file.write_text(json.dumps(job))
    with open(job_file.with_suffix(".out"), "w") as out, open(job_file.with_suffix(".err"), "w") as err:
        return subprocess.Popen([sys.executable, "-m", "blender_gen.worker", str(job_file)], cwd=REPO,
                                stdout=out, stderr=err, text=True)


def run_mode(mode: str, items: list[dict], npz: Path, meta: dict, out: Path, args) -> dict:
    render = {"mode": mode, "samples": args.samples, "max_bounces": 0, "denoise": False, "threads": args.threads,
              "shadow_map_px": args.shadow_map_px, "shadow_map_extent_factor": args.shadow_map_extent_factor,
              "shadow_map_samples": args.shadow_map_samples, "gbuffer_samples": args.gbuffer_samples,
              "shadow_map_levels": args.shadow_map_levels}
    n = args.workers
    blocks = [items[i * len(items) // n:(i + 1) * len(items) // n] for i in range(n)]
    t0 = time.perf_counter()
    procs = []
    for b, block in enumerate(blocks):
        job = {"terrain_npz": str(npz), "terrain_meta": meta,
               "crater": {"name": "bench", "lat": -89.67, "lon": 129.78, "diameter_km": args.diameter_km},
               "hapke": HAPKE, "render": render, "out_dir": str(out / mode), "renders": block}
        job_file = out / f"job-{mode}-{b}.json"
        procs.append((run_block(job, job_file), job_file))
    for p, _ in procs:
        p.wait()
    wall = time.perf_counter() - t0
    stats, n_results = [], 0
    for p, job_file in procs:
        stdout = job_file.with_suffix(".out").read_text()
        stderr = job_file.with_suffix(".err").read_text()
        if p.returncode != 0:
            raise SystemExit(f"worker failed ({p.returncode}):\n{stdout[-2000:]}\n{stderr[-4000:]}")
        n_results += sum(1 for ln in stdout.splitlines() if ln.startswith("RESULT "))
        stats += [json.loads(ln[6:]) for ln in stderr.splitlines() if ln.startswith("STATS ")]
    summary = {"mode": mode, "renders": n_results, "wall_s": round(wall, 2),
               "renders_per_s": round(n_results / wall, 3), "workers": n, "threads_per_worker": args.threads,
               "worker_stats": stats}
    if mode == "fast":
        f = [s["fast"] for s in stats]
        n_maps = sum(x["lit_maps"] for x in f)
        n_gb = sum(x["gbuffers"] for x in f)
        t_map = sum(x["lit_map_s"] for x in f) / max(n_maps, 1)
        t_gb = sum(x["gbuffer_s"] for x in f) / max(n_gb, 1)
        t_shade = sum(x["shade_s"] for x in f) / max(n_results, 1)
        t_write = sum(s["exr_write_s"] for s in stats) / max(n_results, 1)
        t_loop = sum(s["seconds"] for s in stats)
        t_other = (t_loop - sum(x["lit_map_s"] + x["gbuffer_s"] + x["shade_s"] for x in f)
                   - sum(s["exr_write_s"] for s in stats)) / max(n_results, 1)
        # Paper sweep per crater: 150 suns x 150 cameras split sun-major over `n` processes; each
        # process renders 150/n lit maps and (up to) all 150 G-buffers.
        per_proc = 22_500 / n
        t_proc = (150 / n) * t_map + 150 * t_gb + per_proc * (t_shade + t_write + t_other)
        summary["per_stage"] = {"lit_map_s": round(t_map, 3), "gbuffer_s": round(t_gb, 3),
                                "shade_ms_per_render": round(1e3 * t_shade, 2),
                                "exr_write_ms_per_render": round(1e3 * t_write, 2),
                                "other_ms_per_render": round(1e3 * t_other, 2)}
        summary["paper_sweep_estimate"] = {
            "seconds_per_crater": round(t_proc, 1),
            "renders_per_s": round(22_500 / t_proc, 2),
            "note": f"{n} processes x {args.threads} thread(s); lit map shared by 150 cameras, "
                    f"G-buffers cached per process"}
    return summary


def compare(items: list[dict], out: Path, direct_dir: Path | None = None) -> dict:
    from crater_core import exr

    rows = []
    for it in items:
        a, _ = exr.read_exr(str((direct_dir or out / "direct") / it["rel_path"]))
        b, _ = exr.read_exr(str(out / "fast" / it["rel_path"]))
        d_if, f_if = a["IF"], b["IF"]
        lit_px = d_if[a["lit"] > 0.5]
        med = float(np.median(lit_px)) if lit_px.size else float(d_if.mean())
        diff = np.abs(d_if - f_if)
        rows.append({"index": it["index"], "sun": [it["sun_elevation"], it["sun_azimuth"]],
                     "cam": [it["cam_elevation"], it["cam_azimuth"]],
                     "rel_mean": round(float(f_if.mean() / d_if.mean() - 1.0), 5),
                     "mad_over_median": round(float(diff.mean() / med), 5),
                     "frac_gt_10pct": round(float((diff > 0.1 * med).mean()), 5),
                     "lit_mad": round(float(np.abs(a["lit"] - b["lit"]).mean()), 5)})
    agg = {k: round(float(np.mean([abs(r[k]) for r in rows])), 5)
           for k in ("rel_mean", "mad_over_median", "frac_gt_10pct", "lit_mad")}
    agg["max_abs_rel_mean"] = round(float(max(abs(r["rel_mean"]) for r in rows)), 5)
    return {"mean_over_renders": agg, "renders": rows}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--mode", choices=("fast", "direct", "both"), default="fast")
    ap.add_argument("--suns", type=int, default=2)
    ap.add_argument("--cams", type=int, default=20)
    ap.add_argument("--sun-stride", type=int, default=1, help="take every n-th sun of the 150-point grid")
    ap.add_argument("--cam-stride", type=int, default=1, help="take every n-th camera of the 150-point grid")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--samples", type=int, default=16)
    ap.add_argument("--shadow-map-px", type=int, default=512)
    ap.add_argument("--shadow-map-samples", type=int, default=8)
    ap.add_argument("--shadow-map-extent-factor", type=float, default=2.1)
    ap.add_argument("--shadow-map-levels", type=int, default=2)
    ap.add_argument("--direct-from", type=Path, default=None,
                    help="with --mode both: compare with the direct renders of an earlier bench --out dir "
                         "(same angles/terrain options) instead of rendering them again")
    ap.add_argument("--gbuffer-samples", type=int, default=16)
    ap.add_argument("--near", type=int, default=512, help="near-field vertices per side")
    ap.add_argument("--diameter-km", type=float, default=21.0)
    ap.add_argument("--out", type=Path, default=None, help="work dir (default: a new temp dir)")
    args = ap.parse_args(argv)

    out = args.out or Path(tempfile.mkdtemp(prefix="crater_synth_bench_"))
    out.mkdir(parents=True, exist_ok=True)
    npz = out / f"terrain{args.near}.npz"
    meta = synthetic_terrain(npz, args.diameter_km * 1000.0, args.near)
    items = paper_items(args.diameter_km * 1000.0, meta["rim_z_m"], args.suns, args.cams,
                        sun_stride=args.sun_stride, cam_stride=args.cam_stride)
    sizes = [(it["crop"][2] - it["crop"][0]) * (it["crop"][3] - it["crop"][1]) for it in items]
    report = {"out": str(out), "near_vertices": args.near, "renders": len(items),
              "mean_crop_px": round(math.sqrt(float(np.mean(sizes))), 1), "cpu_count": os.cpu_count(),
              "modes": {}}
    modes = ("fast", "direct") if args.mode == "both" else (args.mode,)
    if args.direct_from is not None:
        modes = tuple(m for m in modes if m != "direct")
    for mode in modes:
        report["modes"][mode] = run_mode(mode, items, npz, meta, out, args)
    if args.mode == "both":
        report["fast_vs_direct"] = compare(items, out, args.direct_from and args.direct_from / "direct")
    print(json.dumps(report, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
