"""The identity of a render: a fingerprint of every setting that can change one of its pixels or labels.

A resumed ``crater-synth dataset`` keeps a rendered file only when the identity recorded in its row
(``render_digest``) equals the identity of the render it plans now. The identity is derived from the
whole typed configuration (:class:`crater_core.settings.Settings`), not from a list of keys that
matter: every setting is in it except those of :data:`IGNORED`, each with the reason why it cannot
change a render. A key added to the settings later is therefore in the identity from the start; the
worst a forgotten exclusion can do is render again what did not need it, never keep a stale render.
``tests/test_integrity_dataset.py`` checks that every ignored key exists and that every other one
changes the identity.

The render's own crater entry, its terrain patch (``terrain_id``: DEM bytes, stack, terrain and
detail settings) and the version of the fast path's horizon maps are added; the angles are not: they
are the render's key (crater, sun and camera angles), and each render is planned for its own angles.
"""

from __future__ import annotations

from collections.abc import Iterable

from crater_core.horizon import HORIZON_VERSION
from crater_core.schema import content_key
from crater_core.settings import CraterSettings, Settings, as_plain

# Settings that cannot change a pixel or a label of a render, with why. Dotted keys of Settings.
IGNORED: dict[str, str] = {
    "crater": "the selection of craters; each render's own crater entry is in its identity",
    "launcher": "where, and in how many processes or shards, the sweep runs",
    "render.threads": "CPU threads of a worker: the same pixels (the EXR header leaves them out too)",
    "render.workers": "worker processes: the same pixels (the EXR header leaves them out too)",
    "render.max_retries": "restarts of a dying worker",
    "render.horizon_cache_dir": "where horizon maps are cached; a map is keyed by its own inputs",
    "sweep.name": "names out_dir and run_dir",
    "sweep.sun_elevation": "the sample positions: a render's own angles are its key",
    "sweep.sun_azimuth": "the sample positions: a render's own angles are its key",
    "sweep.cam_elevation": "the sample positions: a render's own angles are its key",
    "sweep.cam_azimuth": "the sample positions: a render's own angles are its key",
    "sweep.min_sun_elevation_deg": "selects which renders of a physical sweep exist, not how one looks",
    "model": "training only: the classifier",
    "train": "training only",
    "sensor": "training only: the sensor model is applied to crops when training, never to an EXR",
    "realset": "training and evaluation only: the real test images",
    "loop": "the closed loop's schedule: which renders exist, not how one looks",
    "figure6": "Figure 6: subsets of a rendered dataset",
    "fetch": "downloads of the data products",
    "validate": "the validation protocol (which craters, which seeds)",
    "ablation": "the ablation's variants are runs with other settings, each with its own identity",
    "data_dir": "where terrain patches are cached; their content is in terrain_id",
    "out_dir": "where the dataset is written",
    "run_dir": "where training writes",
    "trajectory": "navigation frames only (their poses and Sun); a sweep render never reads it",
    "detection": "detection frames only (their conditions and grouping); a sweep render never reads it",
}


def settings_payload(settings: Settings, ignored: Iterable[str]) -> dict:
    """Every setting of ``settings`` as plain data, less the dotted keys of ``ignored``."""
    plain = as_plain(settings)
    for key in ignored:
        head, _, rest = key.partition(".")
        node = plain
        while rest:
            node = node[head]
            head, _, rest = rest.partition(".")
        node.pop(head)
    return plain


def identity_payload(settings: Settings, crater: CraterSettings, terrain_id: str) -> dict:
    """The plain data hashed into :func:`render_identity` (also handy to see why two identities differ)."""
    plain = settings_payload(settings, IGNORED)
    plain["render_crater"] = crater.as_dict()
    plain["terrain_id"] = terrain_id
    if settings.render.mode == "fast":  # fast-mode shadows come from horizon maps (crater_core.horizon)
        plain["horizon_version"] = HORIZON_VERSION
    return plain


def render_identity(settings: Settings, crater: CraterSettings, terrain_id: str) -> str:
    """16 hex digits of the sha256 of :func:`identity_payload` (canonical JSON: crater_core.schema.content_key)."""
    return content_key(identity_payload(settings, crater, terrain_id))
