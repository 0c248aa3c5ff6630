"""Blender scene reset and Cycles setup (CPU, or a GPU backend) from a job's render settings.

Everything the renderer depends on is set explicitly (Cycles' defaults are 4096 samples, denoising on,
12 bounces, a Blackman-Harris pixel filter and a grey world, none of which we want).
"""

from __future__ import annotations

import bpy

from blender_gen import compat, material
from crater_core.settings import RENDER_DEVICES

# Default render settings: equal to configs/render/cycles_cpu.yaml (tests/test_docs_truth.py compares
# them); the job's values win.
RENDER_DEFAULTS = {
    "mode": "fast",
    "device": "CPU",
    "samples": 16,
    "max_bounces": 0,
    "denoise": False,
    "threads": 0,
    "shadow_map_px": 512,
    "shadow_map_extent_factor": 2.45,
    "shadow_map_levels": 2,  # nested horizon-map levels, each shadow_map_px^2, half-widths extent / 2^k
    "gbuffer_samples": 0,  # 0: same as samples
    "seed": 0,
}


def render_settings(job_render: dict | None) -> dict:
    """The job's render dict completed with :data:`RENDER_DEFAULTS` and checked."""
    cfg = dict(RENDER_DEFAULTS)
    cfg.update({k: v for k, v in (job_render or {}).items() if v is not None})
    if cfg["mode"] not in ("direct", "fast"):
        raise ValueError(f"render.mode={cfg['mode']!r}: must be 'direct' or 'fast'")
    if cfg["device"] not in RENDER_DEVICES:
        raise ValueError(f"render.device={cfg['device']!r}: must be one of {', '.join(RENDER_DEVICES)}")
    for key in ("samples", "shadow_map_px", "shadow_map_levels"):
        if int(cfg[key]) < 1:
            raise ValueError(f"render.{key}={cfg[key]}: must be >= 1")
    for key in ("max_bounces", "threads", "gbuffer_samples"):  # an old job's shadow_map_samples is ignored
        if int(cfg[key]) < 0:
            raise ValueError(f"render.{key}={cfg[key]}: must be >= 0")
    if float(cfg["shadow_map_extent_factor"]) <= 0:
        raise ValueError(f"render.shadow_map_extent_factor={cfg['shadow_map_extent_factor']}: must be > 0")
    return cfg


def reset() -> bpy.types.Scene:
    """Empty factory-settings scene (no cube, camera or light)."""
    bpy.ops.wm.read_factory_settings(use_empty=True)
    return bpy.context.scene


def use_device(scene: bpy.types.Scene, device: str) -> None:
    """Render on ``device`` (one of :data:`RENDER_DEVICES`). A GPU backend uses every device of that type
    Cycles finds; none found is a ValueError naming the setting and the devices Cycles does see, never a
    silent fall-back to the CPU."""
    cyc = scene.cycles
    if device == "CPU":
        cyc.device = "CPU"
        return
    prefs = bpy.context.preferences.addons["cycles"].preferences
    try:
        prefs.compute_device_type = device
    except TypeError:  # this Blender's Cycles was built without that backend
        raise ValueError(f"render.device={device}: this Blender's Cycles has no {device} backend") from None
    prefs.refresh_devices()
    gpus = [d for d in prefs.devices if d.type == device]
    if not gpus:
        seen = ", ".join(f"{d.name} ({d.type})" for d in prefs.devices) or "none"
        raise ValueError(f"render.device={device}: Cycles finds no {device} device (devices seen: {seen})")
    for d in prefs.devices:
        d.use = d.type == device
    cyc.device = "GPU"


def setup_cycles(scene: bpy.types.Scene, cfg: dict) -> None:
    """Cycles on ``render.device`` (CPU by default), direct light only by default, no denoiser, box pixel
    filter, black world."""
    scene.render.engine = "CYCLES"
    cyc = scene.cycles
    use_device(scene, str(cfg.get("device", "CPU")))
    cyc.samples = int(cfg["samples"])
    cyc.use_adaptive_sampling = False  # fixed samples: reproducible noise level
    cyc.use_denoising = bool(cfg["denoise"])
    cyc.max_bounces = int(cfg["max_bounces"])
    cyc.diffuse_bounces = int(cfg["max_bounces"])
    cyc.glossy_bounces = 0
    cyc.transmission_bounces = 0
    cyc.volume_bounces = 0
    cyc.transparent_max_bounces = 0
    cyc.caustics_reflective = False
    cyc.caustics_refractive = False
    cyc.sample_clamp_direct = 0.0  # no clamping: I/F is radiometric
    cyc.sample_clamp_indirect = 0.0
    # Cycles' default 0.01 randomly drops shadow rays whose contribution is below it; I/F values are
    # ~0.001-0.1, so that would add heavy noise to the direct render (measured: x80 the pixel noise).
    cyc.light_sampling_threshold = 0.0
    cyc.seed = int(cfg.get("seed", 0))
    cyc.use_animated_seed = False
    # Box filter of one pixel: a pixel is the plain average over its footprint (same in every pass,
    # so the fast path's G-buffer and the direct render integrate the same area).
    cyc.pixel_filter_type = "BOX"
    cyc.filter_width = 1.0
    cyc.film_exposure = 1.0
    cyc.use_auto_tile = False
    compat.set_optional(cyc, "use_light_tree", False)  # one light; Cycles without a light tree (< 3.5) samples it alike
    cyc.use_camera_cull = False
    cyc.use_distance_cull = False

    r = scene.render
    threads = int(cfg["threads"])
    r.threads_mode = "FIXED" if threads > 0 else "AUTO"
    if threads > 0:
        r.threads = threads
    r.film_transparent = False
    r.use_persistent_data = True  # keep the BVH and synced scene between renders
    r.use_compositing = False
    r.use_sequencer = False
    r.resolution_percentage = 100
    r.pixel_aspect_x = r.pixel_aspect_y = 1.0
    r.use_motion_blur = False
    scene.view_settings.view_transform = "Standard"
    scene.view_settings.look = "None"
    scene.view_settings.exposure = 0.0
    scene.view_settings.gamma = 1.0

    world = bpy.data.worlds.new("black")
    for node in compat.node_tree(world).nodes:
        if node.bl_idname == "ShaderNodeBackground":
            node.inputs["Color"].default_value = (0.0, 0.0, 0.0, 1.0)
            node.inputs["Strength"].default_value = 0.0
    world.color = (0.0, 0.0, 0.0)
    scene.world = world

    vl = scene.view_layers[0]
    vl.use_pass_combined = True
    vl.use_pass_z = True
    vl.use_pass_normal = True
    vl.use_pass_diffuse_direct = True
    material.register_aovs(vl)

    compat.set_multilayer_exr_output(r.image_settings)
