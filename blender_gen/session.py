"""The live Blender scene of one worker process: terrain meshes, Hapke material, sun, cameras.

Built once per job (``bpy`` is imported once per process); every render only changes the sun, the
camera, the material mode and the sample count, so Cycles keeps the synced scene and its BVH
(``render.use_persistent_data``).
"""

from __future__ import annotations

import numpy as np

from blender_gen import camera, material, mesh, render, scene, sun
from crater_core import geometry, hapke


class Session:
    def __init__(self, job: dict, terrain: dict):
        self.job = job
        self.cfg = scene.render_settings(job.get("render"))
        self.params = hapke.HapkeParams.from_mapping(job["hapke"])
        self.diameter_m = float(job["crater"]["diameter_km"]) * 1000.0
        self.scene = scene.reset()
        scene.setup_cycles(self.scene, self.cfg)
        self.material = material.build_terrain_material(self.params)
        self.objects = mesh.load_terrain_meshes(terrain, self.material)
        self.sun = sun.create_sun(self.scene)
        self.sun.visible_camera = False
        self.view_cam = camera.create_camera(self.scene, "view")
        self.map_cam = camera.create_camera(self.scene, "map")
        zs = [terrain["near_xyz"][..., 2].max()]
        if terrain.get("far_xyz") is not None:
            zs.append(terrain["far_xyz"][..., 2].max())
        self.z_top = float(max(zs)) + 1000.0
        self.to_sun = None
        self.n_cycles_calls = 0
        self.cycles_seconds = 0.0

    # -- per-render state -------------------------------------------------------------------------
    def set_sun(self, to_sun: np.ndarray) -> None:
        to_sun = np.asarray(to_sun, dtype=np.float64)
        if self.to_sun is not None and np.array_equal(self.to_sun, to_sun):
            return
        self.to_sun = to_sun
        sun.aim_sun(self.sun, to_sun)
        material.set_sun_direction(self.material, to_sun)

    def configure(self, mode: str, samples: int, seed: int | None = None) -> None:
        """Material mode ('hapke' | 'lit' | 'gbuffer'), sun on/off to match, sample count, seed
        (default: the job's render seed; every Cycles call sets it, so no call inherits another's)."""
        material.set_mode(self.material, mode)
        sun.set_enabled(self.sun, mode != "gbuffer")
        cyc = self.scene.cycles
        if cyc.samples != int(samples):
            cyc.samples = int(samples)
        seed = int(self.cfg.get("seed", 0) if seed is None else seed) & 0x7FFFFFFF
        if cyc.seed != seed:
            cyc.seed = seed

    @staticmethod
    def pose(item: dict) -> geometry.CameraPose:
        """The item's camera: its explicit ``camera`` pose (``position`` m and ``rotation`` columns
        right, up, back, in the patch's ENU frame; navigation frames) or the sweep's look-at camera."""
        cam = item.get("camera")
        if cam is not None:
            return geometry.CameraPose(
                position=np.asarray(cam["position"], dtype=np.float64),
                rotation=np.asarray(cam["rotation"], dtype=np.float64).reshape(3, 3),
                fov_deg=float(item["fov_deg"]),
            )
        return geometry.look_at_camera(
            float(item["cam_elevation"]), float(item["cam_azimuth"]), float(item["range_m"]), float(item["fov_deg"])
        )

    def render_view(self, item: dict) -> dict[str, np.ndarray]:
        camera.set_view(self.scene, self.view_cam, self.pose(item), int(item["frame_width"]), item["crop"])
        return self._render()

    def render_top_down(self, half_width_m: float, pixels: int) -> dict[str, np.ndarray]:
        camera.set_top_down(self.scene, self.map_cam, half_width_m, pixels, self.z_top)
        return self._render()

    def _render(self) -> dict[str, np.ndarray]:
        passes, seconds = render.render_passes(self.scene)
        self.n_cycles_calls += 1
        self.cycles_seconds += seconds
        return passes
