"""The Blender API differences the renderer meets, handled by feature (never by version number).

The worker runs under the pip ``bpy`` module (5.0) and under a Blender binary
(``blender --background --python blender_gen/worker.py -- JOB``; Debian ships 3.4). Each difference is
probed on the object at hand, so a version in between gets whichever form it has:

- a new world or material has no node tree until ``use_nodes`` is set (3.x; in 5.0 the tree always
  exists and ``use_nodes`` is deprecated): :func:`node_tree`;
- the render output format: ``image_settings.media_type`` + ``file_format`` (5.0) or the single
  ``file_format = "OPEN_EXR_MULTILAYER"`` (3.x): :func:`set_multilayer_exr_output`;
- mesh polygons built with ``foreach_set``: each polygon's ``loop_total`` is derived from the next
  ``loop_start`` (4.x+, read-only) or must be given as well (3.x, where a zero count crashes Cycles):
  :func:`set_polygon_loops`;
- the AOV an AOV Output node writes: ``aov_name`` (4.x+) or the node's ``name`` (3.x):
  :func:`set_aov_name`;
- render-pass names in the multilayer EXR: "Diffuse Direct" (4.x+) or the short "DiffDir" (3.x):
  :func:`canonical_passes`;
- Cycles settings that not every version has (``use_light_tree``, 3.5+), where an absent setting already
  behaves as the value we would set: :func:`set_optional`.

Also the one place that says which Blender versions the worker supports (:data:`MIN_VERSION`,
:data:`TESTED_VERSIONS`) and checks the running one (:func:`check_version`). Version numbers are used
only there, to refuse a Blender too old to have the features the renderer needs.
"""

from __future__ import annotations

import re

# The oldest Blender with every feature the renderer relies on, each of them probed above or used as
# is: ShaderNodeCombineColor (3.3), Cycles X settings (use_auto_tile, light_sampling_threshold: 3.0),
# view-layer AOVs (2.92). 3.4 is the oldest version actually run (docs/renderer.md, "Blender versions").
MIN_VERSION = (3, 4)
TESTED_VERSIONS = ("3.4.1 (Debian 12 binary)", "5.0.1 (pip bpy module)")


def supported_text() -> str:
    """The supported versions in words, for error messages."""
    return f"supported: Blender {MIN_VERSION[0]}.{MIN_VERSION[1]} or newer (tested: {', '.join(TESTED_VERSIONS)})"


def parse_version(text: str) -> tuple[int, ...] | None:
    """(major, minor, patch) from ``blender --version`` output or a version string ("Blender 3.4.1",
    "5.0.1"); None when there is none."""
    m = re.search(r"(?:^|Blender\s+)(\d+)\.(\d+)(?:\.(\d+))?", text.strip())
    if m is None:
        return None
    return tuple(int(g) for g in m.groups() if g is not None)


def version_problem(version: tuple[int, ...] | None, what: str) -> str | None:
    """None when ``version`` is supported, else one line naming ``what``, the version found and the
    supported versions."""
    if version is None:
        return f"{what}: cannot tell its Blender version; {supported_text()}"
    if tuple(version[:2]) < MIN_VERSION:
        found = ".".join(str(v) for v in version)
        return f"{what} is Blender {found}, too old; {supported_text()}"
    return None


def check_version() -> str | None:
    """The running Blender's problem (see :func:`version_problem`), or None. Imports bpy."""
    import bpy

    return version_problem(tuple(bpy.app.version), f"this Blender ({bpy.app.binary_path or 'bpy module'})")


def version_string() -> str:
    """The running Blender's version, e.g. "3.4.1" (recorded in each EXR header)."""
    import bpy

    return str(bpy.app.version_string)


def node_tree(id_block):
    """The shader node tree of a world or material, creating it where a new one has none yet."""
    if id_block.node_tree is None:
        id_block.use_nodes = True
    return id_block.node_tree


def set_multilayer_exr_output(image_settings) -> None:
    """Render output: one multilayer EXR (every pass), float32, uncompressed."""
    if hasattr(image_settings, "media_type"):  # the format is chosen in two steps: media type, then file format
        image_settings.media_type = "MULTI_LAYER_IMAGE"
    else:
        image_settings.file_format = "OPEN_EXR_MULTILAYER"
    image_settings.color_depth = "32"
    image_settings.exr_codec = "NONE"


def set_polygon_loops(mesh, loop_start, loop_total) -> None:
    """Set every polygon's first loop (int32 array) and, where this Blender stores it, its loop count."""
    import bpy

    mesh.polygons.foreach_set("loop_start", loop_start)
    if not bpy.types.MeshPolygon.bl_rna.properties["loop_total"].is_readonly:
        mesh.polygons.foreach_set("loop_total", loop_total)


def set_aov_name(node, name: str) -> None:
    """Make the AOV Output shader ``node`` write the view-layer AOV ``name``."""
    if hasattr(node, "aov_name"):
        node.aov_name = name
    else:  # the node's own name is the AOV's name (and must then be unique in the tree)
        node.name = name


# Short pass names of older multilayer EXRs -> the names the renderer reads.
PASS_ALIASES = {"DiffDir": "Diffuse Direct"}


def canonical_passes(passes: dict) -> dict:
    """``passes`` (pass name -> array, as read from Cycles' multilayer EXR) under the names the renderer
    reads, whichever form this Blender wrote."""
    out = dict(passes)
    for short, name in PASS_ALIASES.items():
        if short in out and name not in out:
            out[name] = out.pop(short)
    return out


def set_optional(owner, attr: str, value) -> bool:
    """Set ``owner.attr`` where this Blender has it; returns whether it did. Only for settings whose
    absence already behaves as ``value`` (the caller says why)."""
    if not hasattr(owner, attr):
        return False
    setattr(owner, attr, value)
    return True
