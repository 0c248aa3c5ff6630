"""Docs and defaults that must stay true to the code, checked programmatically (no value hard-coded here)."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from crater_synth.config import compose, resolved

ROOT = Path(__file__).resolve().parent.parent
# Keys of the composed render group that only the host reads (never the Blender worker's RENDER_DEFAULTS).
# (The horizon-map cache directory reaches the worker as the job's own `horizon_cache_dir`, not in `render`.)
HOST_ONLY_RENDER_KEYS = {
    "device",
    "crop_to_roi",
    "roi_min_px",
    "workers",
    "max_retries",
    "horizon_cache_dir",
    "blender",
}
# Keys of RENDER_DEFAULTS that are not render-group settings: the Cycles seed comes with each render item
# (crater_synth.dataset derives it from the top-level `seed`); the default is only a fallback.
WORKER_ONLY_RENDER_KEYS = {"seed"}
PACKAGES = ("crater_core", "data_manifest", "blender_gen", "train", "crater_synth")


def test_render_defaults_equal_the_composed_render_config():
    """blender_gen.scene.RENDER_DEFAULTS (what a job without a value gets) == configs/render defaults."""
    from blender_gen.scene import RENDER_DEFAULTS

    render = resolved(compose([]))["render"]
    differ = {
        k: (v, render.get(k, "<absent>"))
        for k, v in RENDER_DEFAULTS.items()
        if k not in WORKER_ONLY_RENDER_KEYS and render.get(k) != v
    }
    assert not differ, f"RENDER_DEFAULTS vs configs/render ((worker, config) per key): {differ}"
    unmirrored = set(render) - set(RENDER_DEFAULTS) - HOST_ONLY_RENDER_KEYS
    assert not unmirrored, (
        f"render keys {sorted(unmirrored)} are in configs/render but not in RENDER_DEFAULTS: "
        f"add them there, or to HOST_ONLY_RENDER_KEYS here if the worker never reads them"
    )


def _doc_files() -> list[Path]:
    return [ROOT / "README.md", *sorted((ROOT / "docs").rglob("*.md"))]


@pytest.mark.parametrize("doc", _doc_files(), ids=lambda p: str(p.relative_to(ROOT)))
def test_every_file_a_doc_names_exists(doc):
    text = doc.read_text(encoding="utf-8")
    named = set(re.findall(r"\b((?:%s|tests|configs|docs)/[\w/.-]+\.(?:py|yaml|md|j2|css))" % "|".join(PACKAGES), text))
    missing = sorted(p for p in named if not (ROOT / p).exists())
    assert not missing, f"{doc.name} names files that do not exist: {missing}"


def test_readme_layout_names_every_package():
    layout = (ROOT / "README.md").read_text(encoding="utf-8").split("## Layout", 1)[1].split("\n## ", 1)[0]
    assert not [p for p in PACKAGES if f"`{p}/`" not in layout]
