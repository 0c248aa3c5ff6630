"""One preprocessing path: geometry of the ROI resampling, and photometric equivalence of a
synthetic I/F crop and an 8-bit version of the same scene."""

import numpy as np
import pytest

from train.errors import TrainError
from train.preprocess import PreprocessConfig, SensorModel, normalize, outside_fraction, preprocess_crop, resample_box
from train.toydata import render_toy

PP = PreprocessConfig()


@pytest.fixture(scope="module")
def scene():
    """A toy crater scene in I/F (float), 96x96 with the rim 64 px across, low sun."""
    return render_toy(2, 96, 64.0, 8.0, 200.0, 90.0, 30.0, terrain_seed=3)["IF"]


def _stats(x):
    return np.array([x.mean(), x.std(), *np.percentile(x, [25, 50, 75, 95])])


@pytest.mark.parametrize("rotation", [0.0, 33.0])
@pytest.mark.parametrize("offset_dn", [0, 4])
def test_if_and_8bit_versions_of_a_scene_give_the_same_statistics(scene, rotation, offset_dn):
    box = (48 - 44.8, 48 - 44.8, 48 + 44.8, 48 + 44.8)  # sigma 1.4 of a 64 px rim
    gain = 230.0 / float(scene.max())  # linear camera, unknown exposure
    dn8 = np.clip(np.rint(scene * gain + offset_dn), 0, 255).astype(np.uint8)
    a = preprocess_crop(scene, box, PP, rotation_deg=rotation)
    b = preprocess_crop(dn8, box, PP, rotation_deg=rotation)
    assert a.shape == b.shape == (150, 150) and a.dtype == b.dtype == np.float32
    assert 0.0 <= a.min() and a.max() <= 1.0
    np.testing.assert_allclose(_stats(a), _stats(b), atol=0.02)
    assert np.mean(np.abs(a - b)) < 0.02


def test_normalize_is_affine_invariant_and_handles_dark_images():
    rng = np.random.default_rng(0)
    x = rng.gamma(0.5, 0.05, size=(150, 150)).astype(np.float32)
    np.testing.assert_allclose(normalize(x, PP), normalize(7.0 * x + 0.3, PP), atol=1e-5)
    assert not normalize(np.zeros((150, 150)), PP).any()  # fully shadowed -> zeros, no NaN
    y = normalize(np.where(np.arange(150 * 150).reshape(150, 150) == 7, 1.0, 0.0), PP)
    assert np.isfinite(y).all() and y.max() == 1.0


def test_resample_box_geometry_and_rotation_without_black_corners():
    # A linear ramp in u: sampling a box returns the ramp over the box, pixel centres at i + 0.5.
    ramp = np.tile(np.arange(200, dtype=np.float32) + 0.5, (200, 1))  # value = u coordinate of the centre
    out = resample_box(ramp, (50, 60, 125, 135), 150, antialias=False)
    expected = 50 + (np.arange(150) + 0.5) * 0.5
    np.testing.assert_allclose(out[75], expected, atol=1e-3)
    # Rotation of the sampling grid: constant image stays constant (no empty corners).
    const = np.full((300, 300), 5.0, dtype=np.float32)
    rot = resample_box(const, (100, 100, 200, 200), 150, rotation_deg=45.0)
    np.testing.assert_allclose(rot, 5.0)
    # Grid rotated 90 degrees counter-clockwise == the crop's content turned clockwise (np.rot90 k=-1).
    img = np.random.default_rng(1).random((120, 120)).astype(np.float32)
    r0 = resample_box(img, (10, 10, 110, 110), 100, antialias=False, order=1)
    r90 = resample_box(img, (10, 10, 110, 110), 100, rotation_deg=90.0, antialias=False, order=1)
    np.testing.assert_allclose(r90, np.rot90(r0, -1), atol=1e-4)


def test_antialiasing_removes_aliasing():
    # A checkerboard at the source Nyquist frequency must average out when shrunk 4x.
    cb = (np.indices((600, 600)).sum(0) % 2).astype(np.float32)
    aa = resample_box(cb, (0, 0, 600, 600), 150, antialias=True)
    assert abs(aa.mean() - 0.5) < 0.01 and aa.std() < 0.05


def test_outside_fraction_and_degenerate_box():
    assert outside_fraction((0, 0, 10, 10), (10, 10)) == 0
    assert outside_fraction((0, 0, 10, 10), (10, 10), rotation_deg=45) > 0.2
    with pytest.raises(TrainError, match="degenerate"):
        resample_box(np.zeros((10, 10)), (5, 5, 5, 9), 8)


def test_sensor_model_is_seeded_and_quantised(scene):
    crop = resample_box(scene, (0, 0, 96, 96), 150) * (0.2 / float(scene.max()))  # below full well
    s = SensorModel(resolution_min_px=48, resolution_prob=1.0)
    a = s.apply(crop, np.random.default_rng(5))
    b = s.apply(crop, np.random.default_rng(5))
    c = s.apply(crop, np.random.default_rng(6))
    np.testing.assert_array_equal(a, b)
    assert not np.array_equal(a, c)
    # After normalisation the noisy image still resembles the clean one.
    assert np.mean(np.abs(normalize(a) - normalize(crop))) < 0.12
    # At the crop's own resolution the output is quantised to 8 bits.
    q = SensorModel(resolution_min_px=0).apply(crop, np.random.default_rng(5))
    assert np.allclose(q * 255, np.rint(q * 255), atol=1e-4)


def test_sensor_model_samples_at_the_real_products_gsd(scene):
    """With gsd_m the crop is integrated on the real sensor's grid (box side / GSD pixels), quantised
    and JPEG-compressed there, then up-sampled like a real crop: a 21 km sigma-1 box at 400 m/px is a
    52-px image, so the result carries no more detail than 52 samples across."""
    crop = resample_box(scene, (0, 0, 96, 96), 150) * (0.2 / float(scene.max()))
    s = SensorModel(
        gsd_m=400.0, jpeg_quality=81, psf_sigma_px=0.0, gain_jitter=0.0, read_noise_dn=0.0, photons_at_full_well=1e9
    )
    out = s.apply(crop, np.random.default_rng(1), box_side_m=21_000.0)
    assert out.shape == crop.shape

    def detail_beyond_52px(img):  # relative change when squeezed through a 52-px grid and back
        native = resample_box(img, (0, 0, 150, 150), 52, antialias=True)
        back = resample_box(native, (0, 0, 52, 52), 150, antialias=False)
        return np.mean(np.abs(back - img)) / np.mean(np.abs(img))

    noise = 0.05 + 0.1 * np.random.default_rng(2).random((150, 150)).astype(np.float32)  # detail at every scale
    plain = SensorModel(gsd_m=400.0, psf_sigma_px=0.0, gain_jitter=0.0, read_noise_dn=0.0, photons_at_full_well=1e9)
    sampled = plain.apply(noise, np.random.default_rng(1), box_side_m=21_000.0)
    assert detail_beyond_52px(sampled) < 0.25 * detail_beyond_52px(noise)
    assert np.mean(np.abs(normalize(out) - normalize(crop))) < 0.15  # still the same scene
    fine = s.apply(crop, np.random.default_rng(1), box_side_m=150 * 400.0 * 2)  # native grid finer than crop
    assert np.allclose(fine * 255, np.rint(fine * 255), atol=1e-4)  # left at crop size: quantised only


def test_jpeg_roundtrip_changes_little_but_something():
    from train.preprocess import jpeg_roundtrip

    x = np.clip(np.random.default_rng(0).random((64, 64)), 0, 1)
    x = np.rint(x * 255) / 255
    y = jpeg_roundtrip(x, 81)
    assert y.shape == x.shape and y.dtype == np.float32
    assert 0 < np.mean(np.abs(y - x)) < 0.2
    assert np.array_equal(jpeg_roundtrip(x, 81), y)  # deterministic


def test_mosaic_composite_max_and_patches():
    """Mosaic composite: max is the per-pixel brightest frame; patches take each pixel from exactly one
    frame, in cells (both frames present, contiguous regions), and one frame passes through."""
    from train.preprocess import mosaic_composite

    rng = np.random.default_rng(0)
    a, b = rng.random((32, 32)).astype(np.float32), rng.random((32, 32)).astype(np.float32)
    np.testing.assert_array_equal(mosaic_composite([a, b], rng, "max"), np.maximum(a, b))
    np.testing.assert_array_equal(mosaic_composite([a], rng, "patches"), a)
    zeros, ones = np.zeros((40, 40), np.float32), np.ones((40, 40), np.float32)
    got = mosaic_composite([zeros, ones], np.random.default_rng(3), "patches", patches=12)
    assert set(np.unique(got)) == {0.0, 1.0}
    # cells, not salt-and-pepper: few label changes along rows
    assert np.abs(np.diff(got, axis=1)).sum() < 40 * 6
    with pytest.raises(TrainError, match="mosaic blend 'median'"):
        mosaic_composite([a, b], rng, "median")


def test_mosaic_partners_share_crater_pose_and_sigma():
    """The frames composited with a sample are the same crater, camera pose and sigma, never itself,
    and only among the given split's samples."""
    from train.data import CropCache, same_pose_partners

    rows = [
        {"crater": c, "cam_elevation": ce, "cam_azimuth": ca, "sun_azimuth": sa}
        for c in ("x", "y")
        for ce in (90.0, 70.0)
        for ca in (0.0,)
        for sa in (0.0, 90.0, 180.0)
    ]
    samples = [(i, s) for i in range(len(rows)) for s in (1.0, 1.4)]
    cache = CropCache(path=None, images=np.zeros((len(samples), 2, 2)), samples=samples)
    split = [j for j, (ri, _) in enumerate(samples) if rows[ri]["sun_azimuth"] != 180.0 or ri < 6]
    partners = same_pose_partners(cache, split, rows)
    for j in split:
        ri, s = samples[j]
        assert j not in partners[j]
        for o in partners[j]:
            assert o in split
            ro, so = samples[o]
            assert (rows[ro]["crater"], rows[ro]["cam_elevation"], so) == (
                rows[ri]["crater"],
                rows[ri]["cam_elevation"],
                s,
            )
    assert len(partners[split[0]]) == 2


def test_disc_support_keeps_the_inscribed_disc_only(scene):
    disc = PreprocessConfig(support="disc")
    box = (48 - 44.8, 48 - 44.8, 48 + 44.8, 48 + 44.8)
    sq, dc = preprocess_crop(scene, box, PP), preprocess_crop(scene, box, disc, rotation_deg=0.0)
    n = PP.size
    c = (np.arange(n) + 0.5) - n / 2
    inside = c[None, :] ** 2 + c[:, None] ** 2 <= (n / 2) ** 2
    np.testing.assert_array_equal(dc[inside], sq[inside])  # the real and synthetic path: mask last
    assert (dc[~inside] == 0).all() and sq[~inside].any()


def test_rotating_a_disc_crop_is_a_camera_roll(scene):
    """Turning a disc-support crop by any angle stays inside the box, and by a right angle it equals
    the exact rotation (what the right-angle augmentation does)."""
    from train.preprocess import apply_support, rotate_crop

    disc = PreprocessConfig(support="disc")
    box = (48 - 44.8, 48 - 44.8, 48 + 44.8, 48 + 44.8)
    y = preprocess_crop(scene, box, disc)
    r90 = apply_support(rotate_crop(y, 90.0), disc)
    np.testing.assert_allclose(r90, np.rot90(y), atol=1e-5)
    r33 = apply_support(rotate_crop(y, 33.0), disc)
    real33 = preprocess_crop(scene, box, disc, rotation_deg=-33.0)  # the real crops' rotated sampling grid
    assert abs(r33.mean() - real33.mean()) < 0.02
    assert np.abs(r33 - real33).mean() < 0.02  # same pixels (bilinear twice vs once)
    assert np.abs(r33 - preprocess_crop(scene, box, disc, rotation_deg=33.0)).mean() > 0.1  # the sense matters


def test_any_angle_augmentation_rolls_disc_crops():
    from train.data import CropCache, SyntheticCropDataset

    cache = CropCache(
        path=None, images=np.random.default_rng(0).random((4, 150, 150)).astype(np.float32), samples=[(0, 1.0)] * 4
    )
    rows = [{"crater": "x", "path": "x.exr"}]
    ds = SyntheticCropDataset(
        cache, [0, 1], [0, 0], rows, PreprocessConfig(support="disc"), None, 0, train=True, augment=True, rotation="any"
    )
    a = ds.image(0)
    ds.set_epoch(1)
    b = ds.image(0)
    assert a[0, 0] == 0 and b[0, 0] == 0 and not np.allclose(a, b)  # a new roll every epoch, corners empty


def test_rotate_crop_shift_moves_content_and_matches_plain_rotation():
    from train.preprocess import rotate_crop

    y = np.random.default_rng(0).random((150, 150)).astype(np.float32)
    moved = rotate_crop(y, 0.0, (5.0, -3.0))  # 5 px right, 3 px up
    np.testing.assert_array_equal(moved[10:140, 10:140], y[13:143, 5:135])
    assert (moved[:, :5] == 0).all()  # what enters the square is 0
    from scipy import ndimage

    plain = ndimage.rotate(y, 33.0, reshape=False, order=1, mode="constant", cval=0.0)
    # OpenCV's warp rounds sample coordinates to 1/32 px: 1/64 px times a step of at most 1 along each axis.
    np.testing.assert_allclose(rotate_crop(y, 33.0, (1e-12, 0.0)), plain, atol=2.0 / 64.0 + 1e-6)


def test_slewing_augmentation_moves_the_crop():
    from train.data import CropCache, SyntheticCropDataset

    img = np.zeros((1, 150, 150), np.float32)
    img[0, 70:80, 70:80] = 1.0  # a bright square at the centre
    cache = CropCache(path=None, images=img, samples=[(0, 1.0)])
    rows = [{"crater": "x", "path": "x.exr"}]
    ds = SyntheticCropDataset(
        cache, [0], [0], rows, PreprocessConfig(support="disc"), None, 0, train=True, augment=True, offset_frac=0.08
    )
    centres = []
    for epoch in range(8):
        ds.set_epoch(epoch)
        y = ds.image(0)
        v, u = np.nonzero(y > 0.5)
        centres.append((u.mean() - 75.0, v.mean() - 75.0))
    c = np.abs(np.array(centres))
    assert c.max() <= 0.08 * 150 + 1.0 and c.max() > 1.0  # moved, within the slewing bound


@pytest.fixture(scope="module")
def plain_config():
    """The default configuration as a plain mapping (what Settings.from_config converts)."""
    from crater_synth.config import load_settings

    return load_settings([]).as_dict()


@pytest.mark.parametrize(
    "key, value, message",
    [
        ("sensor.jpeg_quality", 0, "sensor.jpeg_quality=0: must lie in [1, 100]"),
        ("sensor.gsd_m", -1.0, "sensor.gsd_m=-1.0: must be > 0 metres"),
        ("sensor.mosaic_blend", "median", "sensor.mosaic_blend='median': must be max or patches"),
        ("sensor.mosaic_frames", 0, "sensor.mosaic_frames=0: must lie in [1, 64]"),
        ("train.preprocess.support", "circle", "train.preprocess.support='circle': must be square or disc"),
        ("train.augment_offset_frac", 0.5, "train.augment_offset_frac=0.5: must lie in [0, 0.25]"),
        ("train.augment_offset_frac", 0.08, "train.augment_offset_frac=0.08: needs train.preprocess.support=disc"),
        ("train.augment_rotation", "any", "train.augment_rotation='any': needs train.preprocess.support=disc"),
        ("model.conv1.stride", 2, "model.conv1.stride=2: must be 1"),
        ("model.input_size", 12, "model.input_size=12: too small for conv1 kernel 7"),
        ("realset.include_embedded", False, "realset.include_embedded=False: leaves the real test set empty"),
    ],
)
def test_the_settings_check_the_training_ranges_once(plain_config, key, value, message):
    """train/ checks no configuration value itself: the settings refuse it, naming the full key."""
    import copy

    from crater_core.settings import Settings, SettingsError

    cfg = copy.deepcopy(plain_config)
    *path, last = key.split(".")
    node = cfg
    for part in path:
        node = node[part]
    node[last] = value
    with pytest.raises(SettingsError) as err:
        Settings.from_config(cfg)
    assert str(err.value).startswith(message)


def test_runtime_preprocessing_and_sensor_are_the_settings(plain_config):
    """PreprocessConfig / SensorModel carry exactly the fields of their settings (plus the crop size)."""
    from dataclasses import asdict

    from crater_core.settings import Settings

    s = Settings.from_config(plain_config)
    pp = PreprocessConfig.from_settings(s.train.preprocess, s.model.input_size)
    assert asdict(pp) == {"size": s.model.input_size, **asdict(s.train.preprocess)}
    assert list(asdict(pp)) == ["size", *asdict(s.train.preprocess)]  # the order the checkpoint records
    assert asdict(SensorModel.from_settings(s.sensor)) == asdict(s.sensor)
