"""Truth labels of a rendered navigation frame, and the reader of a ``nav-frames`` manifest.

Every landmark of the map whose 3-D rim-centre point projects inside the frame is labelled with its
projected rim ellipse (the rim circle in the landmark's own local horizontal plane: the Moon's curvature
tilts it against the frame's), its **lit-rim fraction** (mean of the ``lit`` channel at ``rim_fractions.RIM_POINTS``
points of the ellipse inside the frame) and its **occluded-rim fraction** (the share of the 3-D rim
points that nearer relief hides in the rendered ``depth``); docs/navigation/rendered.md. A label's
fields, in order, are ``crater_core.schema.NAVFRAME_LANDMARK_FIELDS``.

Each row records the landmark map its labels were computed with (:func:`.landmarks.map_identity`); the
readers of truth (:func:`labelled_rows`) refuse a row whose map is not the pole's committed one, and
``crater-synth nav-frames-relabel DIR`` computes the labels again from the frames' own EXRs.
"""

from __future__ import annotations

import json
from pathlib import Path

import click
import numpy as np

from crater_core import exr, geometry, schema
from crater_core.rim_fractions import hidden_rim_fraction, lit_rim_fraction, rim_circle
from crater_core.trajectory import FramePose
from crater_core.verify_file import rows_faults
from crater_synth.cli_common import user_errors
from crater_synth.errors import UserError
from crater_synth.navigation.georef import pole_of
from crater_synth.navigation.map.landmarks import default_map_identity, load_default_map, positions_mc
from crater_synth.navigation.rendered.frame_folder import KIND as FRAMES_KIND
from crater_synth.outfolder import OutFolder

# A rim point is hidden when the rendered depth there is nearer than the rim point itself by more than
# this margin: a fixed part (terrain detail) plus a share of the diameter (a real rim crest rises and falls
# around the map's mean rim height, by a few per cent of D); relief in front of a rim in an oblique view
# is nearer by far more.
OCCLUSION_MARGIN_M = 1000.0
OCCLUSION_MARGIN_D = 0.05
FRAME_LABEL_VERSION = 3  # 2: labels carry occluded_rim_fraction; 3: rows record their landmark map
# A label whose 3-D rim is more than half hidden behind nearer relief is no rim ellipse a detector could
# see: nav-frames-eval counts it neither as a miss nor towards the landmarks a fix could use, and a
# detection on it not as false. Half: most of the ellipse must be in sight to fit it (an assumption, not
# tuned: on the committed trajectories no label is past a quarter hidden).
HIDDEN_RIM_MAX = 0.5
# The fields every reader of a nav-frames row (evaluation, navigate, relabel, lost-in-space) looks up.
FRAME_ROW_FIELDS = ("trajectory", "index", "rel_path", "sha256", "frame_origin", "pose", "landmarks")


def hidden(label: dict) -> bool:
    """Whether the label's rim is mostly hidden (:data:`HIDDEN_RIM_MAX`; labels before version 2 carry no
    fraction and count as seen)."""
    frac = label.get("occluded_rim_fraction")
    return frac is not None and frac > HIDDEN_RIM_MAX


def occluded_rim_fraction(depth: np.ndarray, rim_uv: np.ndarray, rim_depth: np.ndarray, diameter_m: float):
    """:func:`crater_core.rim_fractions.hidden_rim_fraction` with the landmark's occlusion margin
    (:data:`OCCLUSION_MARGIN_M` + :data:`OCCLUSION_MARGIN_D` x ``diameter_m``)."""
    return hidden_rim_fraction(depth, rim_uv, rim_depth, OCCLUSION_MARGIN_M + OCCLUSION_MARGIN_D * diameter_m)


def landmarks_in_view(
    pose: FramePose,
    landmarks,
    lat0: float,
    lon0: float,
    lit: np.ndarray | None = None,
    depth_image: np.ndarray | None = None,
) -> list[dict]:
    """Labels of every landmark whose rim-centre point projects inside the frame (in front of the camera);
    with the frame's ``lit`` and ``depth`` channels, each rim's lit and occluded fractions."""
    if not landmarks:
        return []
    cam = pose.pose_enu(lat0, lon0)
    w = int(pose.width_px)
    pts_mc = positions_mc(landmarks)
    pts = geometry.mc_to_enu(pts_mc, lat0, lon0)
    uv, depth = geometry.project_points(pts, cam, w)
    inside = (depth > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < w) & (uv[:, 1] >= 0) & (uv[:, 1] < w)
    basis = geometry.enu_basis(lat0, lon0)
    out = []
    for k in np.nonzero(inside)[0]:
        lm = landmarks[k]
        normal = basis @ (pts_mc[k] / np.linalg.norm(pts_mc[k]))  # the landmark's local up, in the frame's ENU
        ell = geometry.project_circle(pts[k], normal, lm.diameter_km * 500.0, cam, w)
        row = {
            "id": lm.id,
            "name": lm.name,
            "diameter_km": lm.diameter_km,
            "lat": lm.lat,
            "lon": lm.lon,
            "centre_px": [round(float(uv[k, 0]), 3), round(float(uv[k, 1]), 3)],
            "depth_m": round(float(depth[k]), 1),
            "ellipse": {key: round(float(v), 4) for key, v in ell.as_dict().items()},
            "rim_inside": bool(
                ell.cu - ell.a >= 0 and ell.cv - ell.a >= 0 and ell.cu + ell.a <= w and ell.cv + ell.a <= w
            ),
        }
        if lit is not None:
            frac = lit_rim_fraction(lit, ell)
            row["lit_rim_fraction"] = None if frac is None else round(frac, 4)
        if depth_image is not None:
            radius = lm.diameter_km * 500.0
            rim = rim_circle(pts[k], normal, radius)
            rim_uv, rim_depth = geometry.project_points(rim, cam, w)
            hidden = occluded_rim_fraction(depth_image, rim_uv, rim_depth, 2.0 * radius)
            row["occluded_rim_fraction"] = None if hidden is None else round(hidden, 4)
        out.append(row)
    return out


def frame_rows(frames_dir) -> list[dict]:
    """The rows of a ``nav-frames`` directory's manifest; a missing, empty or unreadable one is one error line."""
    manifest = Path(frames_dir) / schema.MANIFEST_NAME
    if not manifest.is_file():
        raise UserError(f"{frames_dir}: no {schema.MANIFEST_NAME} (render with `crater-synth nav-frames` first)")
    rows = []
    for n, raw in enumerate(manifest.read_bytes().splitlines(), 1):
        if not raw.strip():
            continue
        try:
            row = json.loads(raw.decode("utf-8"))
        except UnicodeDecodeError as exc:
            raise UserError(f"{manifest} line {n}: not UTF-8 text (byte 0x{raw[exc.start]:02x})") from None
        except (ValueError, RecursionError):
            raise UserError(f"{manifest} line {n}: not a JSON row") from None
        if not isinstance(row, dict):
            raise UserError(f"{manifest} line {n}: JSON but not a row (a JSON object)")
        missing = [f for f in FRAME_ROW_FIELDS if f not in row]
        if missing:
            # A `crater-synth dataset` manifest is the likely mix-up: its rows name a crater and a path.
            what = "a render dataset's row (`crater-synth dataset`)" if "crater" in row and "path" in row else "a row"
            raise UserError(
                f"{manifest} line {n}: {what} without the nav-frames field(s) {missing}: "
                "not a `crater-synth nav-frames` manifest"
            )
        rows.append(row)
    if not rows:
        raise UserError(f"{manifest}: no frames")
    return rows


def labelled_rows(frames_dir, only: str | None = None) -> list[dict]:
    """:func:`frame_rows` for a reader of the labels as truth: one error line when a row's labels were
    computed with another landmark map than its pole's committed one (a map rebuilt or edited numbers its
    landmarks anew: the labels would name the wrong craters) or with a map they did not record, and when
    a frame fails verify's check (:func:`checked_frames`). ``only``: the frame of that ``rel_path`` alone
    is checked (``navigate FRAME.exr``)."""
    rows = frame_rows(frames_dir)
    checked_frames(frames_dir, [r for r in rows if only is None or r.get("rel_path") == only])
    current: dict[str, dict] = {}
    for row in rows:
        pole = pole_of(row["frame_origin"]["lat"])
        if pole not in current:
            current[pole] = default_map_identity(pole)
        now, was = current[pole], row.get("landmark_map") or {}
        if was.get("sha256") != now["sha256"]:
            made = (
                f"landmark map sha256 {str(was['sha256'])[:12]} ({was.get('landmarks')} landmarks)"
                if was.get("sha256")
                else "a landmark map the row does not record (labels before version 3)"
            )
            raise UserError(
                f"{frames_dir}: frame {row.get('index')} was labelled with {made}, but the committed {pole} map "
                f"is sha256 {now['sha256'][:12]} ({now['landmarks']} landmarks): relabel the frames with "
                f"`crater-synth nav-frames-relabel {frames_dir}` (the rendered EXRs are kept)"
            )
    return rows


def checked_frames(frames_dir, rows: list[dict]) -> None:
    """verify's check of each row's frame (:func:`crater_core.verify_file.file_faults` without decoding:
    inside the folder, its sha256, and the pose, Sun and frame its header records), unless a recorded
    ``crater-synth verify`` covers the file unchanged; the first fault is one error line."""
    faults = rows_faults("navframe", frames_dir, rows)
    if faults:
        more = f" (and {len(faults) - 1} more)" if len(faults) > 1 else ""
        raise UserError(f"{faults[0]}{more}: `crater-synth verify {frames_dir}` lists every fault")


def relabel(frames_dir) -> dict:
    """Compute every frame's labels again with its pole's committed map, from the pose its row records and
    the lit and depth channels of its EXR (checked against the row's sha256 first); the manifest is
    rewritten at once (atomically) when every frame is done. Returns a summary: how many frames' labels
    changed, and how many rows recorded another map (or none).

    Holds the folder's lock (the one ``nav-frames`` takes: crater_synth.outfolder), so neither runs while
    the other writes; the folder's marker, when it lists the manifest, records the rewritten one."""
    frames_dir = Path(frames_dir)
    folder = OutFolder(frames_dir, FRAMES_KIND, flag="FRAMES_DIR")
    if frames_dir.is_dir():
        folder.lock()
    try:
        done = _relabel(frames_dir, folder)
    except BaseException:
        folder.discard()  # the lock file too, if this run created it
        raise
    folder.release()
    return done


def _relabel(frames_dir: Path, folder: OutFolder) -> dict:
    rows = frame_rows(frames_dir)
    if rows:
        folder.subject = rows[0].get("trajectory")
        folder.check()  # a folder of another kind or trajectory is refused; reads the files its marker lists
    maps: dict[str, tuple] = {}
    changed = remapped = 0
    for row in rows:
        path = frames_dir / row["rel_path"]
        if not path.is_file() or schema.sha256_file(path) != row.get("sha256"):
            raise UserError(
                f"{path}: missing, or its sha256 differs from its manifest row: nothing relabelled "
                "(render the frames again with `crater-synth nav-frames`)"
            )
        pose = FramePose.from_dict(row["pose"])
        pole = pole_of(row["frame_origin"]["lat"])
        if pole not in maps:
            maps[pole] = (load_default_map(pole)[0], default_map_identity(pole))
        try:
            channels = exr.read_channels(path, ("lit", "depth"))
            lit, depth = channels["lit"], channels["depth"]
        except exr.ExrError as exc:
            raise UserError(f"{path}: {exc}; nothing relabelled") from None
        labels = landmarks_in_view(pose, maps[pole][0], pose.target_lat, pose.target_lon, lit, depth)
        changed += labels != row["landmarks"]
        remapped += row.get("landmark_map") != maps[pole][1]
        row.update(landmarks=labels, label_version=FRAME_LABEL_VERSION, landmark_map=maps[pole][1])
    manifest = frames_dir / schema.MANIFEST_NAME
    schema.atomic_write_text(manifest, "".join(schema.dumps_row(r) + "\n" for r in rows))
    if folder.owns(schema.MANIFEST_NAME):
        folder.seal([schema.MANIFEST_NAME])
    return {
        "frames_dir": str(frames_dir),
        "frames": len(rows),
        "labels_changed": changed,
        "map_record_changed": remapped,
    }


@click.command("nav-frames-relabel")
@click.argument("frames_dir", type=click.Path(path_type=Path))
@user_errors
def nav_frames_relabel_command(frames_dir):
    """Label a `nav-frames` directory's frames again with the committed landmark map (after the map changed).

    The labels (every landmark in view, its rim ellipse, lit and occluded rim fractions) are computed from
    each frame's recorded pose and its EXR; nothing is rendered. Example:
    `crater-synth nav-frames-relabel data/navframes/descent_ridge`.
    """
    click.echo(json.dumps(relabel(frames_dir)))
