"""Depth sensor models (envs.sensors) on real scenes, and the camera-only surroundings of a scene."""

from __future__ import annotations

import mujoco
import numpy as np
import pytest
from scipy import ndimage

from envs import camera, sensors
from envs import scene as scene_lib
from envs.objects import tiny_object_set

IDENTITY = [1.0, 0.0, 0.0, 0.0]
SMALL = camera.CameraConfig(width=160, height=120)
NOISY = ("kinect", "realsense", "stereo")


@pytest.fixture(scope="module")
def objects():
    return {asset.name: asset for asset in tiny_object_set()}


@pytest.fixture(scope="module")
def scene(objects):
    """A 12 cm box standing and a cylinder beside it: tall edges against the table."""
    return scene_lib.arrange_scene(
        [objects["tiny/box_b"], objects["tiny/cylinder"]],
        [[-0.05, 0.0, 0.06, *IDENTITY], [0.1, 0.05, 0.05, *IDENTITY]],
    )


@pytest.fixture(scope="module")
def table_only(objects):
    """The table alone: the one box is placed past the workspace edge and removed."""
    scene = scene_lib.arrange_scene([objects["tiny/box_a"]], [[0.3, 0.0, 0.026, *IDENTITY]])
    assert not scene.present.any()
    return scene


def test_exact_is_the_renderer_and_noise_is_seeded(scene):
    exact = sensors.sense(scene, SMALL, "exact")
    np.testing.assert_array_equal(exact.depth, exact.truth.depth)
    np.testing.assert_array_equal(exact.depth, camera.observe(scene, SMALL).depth)
    assert exact.depth.dtype == np.float32
    for name in NOISY:
        a = sensors.sense(scene, SMALL, name, seed=3)
        b = sensors.sense(scene, SMALL, sensors.get_sensor(name), seed=3)
        np.testing.assert_array_equal(a.depth, b.depth)
        np.testing.assert_array_equal(a.truth.depth, exact.depth)
        other = sensors.sense(scene, SMALL, name, seed=4)
        assert (other.depth != a.depth).mean() > 0.3
        assert a.depth.dtype == np.float32 and a.depth.shape == exact.depth.shape
        assert np.isfinite(a.depth).all() and (a.depth >= 0).all()
        assert 0.8 < (a.depth > 0).sum() / (exact.depth > 0).sum() < 1.0  # some depth lost, most kept


def _interior_table(truth: camera.Observation, margin: int) -> np.ndarray:
    """Table pixels at least `margin` pixels from anything else (objects, no return, the image border)."""
    table = truth.labels == scene_lib.TABLE
    table[[0, -1], :] = table[:, [0, -1]] = False
    return ndimage.binary_erosion(table, iterations=margin)


@pytest.mark.parametrize("name", NOISY)
def test_axial_noise_on_the_table_matches_the_model(scene, name):
    sensor = sensors.get_sensor(name)
    errors, sigmas = [], []
    for seed in range(3):
        sensed = sensors.sense(scene, SMALL, name, seed=seed)
        truth = sensed.truth.depth.astype(np.float64)
        keep = _interior_table(sensed.truth, 4) & (sensed.depth > 0)
        errors.append(sensed.depth[keep] - truth[keep])
        sigmas.append(sensors.axial_sigma(sensor, truth[keep]))
    error, sigma = np.concatenate(errors), np.concatenate(sigmas)
    assert len(error) > 20000
    assert 0.5 < truth[truth > 0].min() and truth.max() < 1.0  # the table at 0.5-1 m
    # The published sigma is the output's total RMS (quantisation included), 1-3 mm here.
    ratio = np.sqrt(np.mean(error**2) / np.mean(sigma**2))
    assert 0.9 < ratio < 1.1, ratio
    assert abs(np.mean(error)) < 0.1 * np.sqrt(np.mean(sigma**2))
    assert 0.9 < np.std(error / sigma) < 1.1
    # Grows with depth as modelled: the far half of the table is noisier by the model's factor.
    far = sigma > np.median(sigma)
    measured = np.std(error[far]) / np.std(error[~far])
    modelled = np.sqrt(np.mean(sigma[far] ** 2) / np.mean(sigma[~far] ** 2))
    assert abs(measured / modelled - 1) < 0.15, (measured, modelled)


def test_axial_sigma_formulas():
    kinect, realsense = sensors.get_sensor("kinect"), sensors.get_sensor("realsense")
    np.testing.assert_allclose(sensors.axial_sigma(kinect, np.array([0.4, 1.4])), [0.0012, 0.0031])
    # Intel: RMS = z^2 * 0.08 px / (f b): 1 m -> 1 / (383 * 0.05) * 0.08 = 4.18 mm.
    np.testing.assert_allclose(sensors.axial_sigma(realsense, np.array([1.0])), [0.08 / (383 * 0.05)])
    assert (sensors.gaussian_sigma(kinect, np.array([0.7])) < sensors.axial_sigma(kinect, np.array([0.7]))).all()


def test_occlusion_shadow_lies_beside_objects_away_from_the_second_eye(scene, table_only):
    config = camera.CameraConfig(width=320, height=240)
    truth = camera.observe(scene, config)
    shadow = sensors.occlusion_shadow(scene, config, truth, baseline=0.075)
    assert 50 < shadow.sum() < 0.05 * (truth.depth > 0).sum()
    # Each shadow run along a row: the surface right after it (towards the second eye at +x) is nearer
    # than the one before it: the band is left of an object's edge.
    depth = truth.depth
    rows, cols = np.nonzero(shadow)
    width = depth.shape[1]
    index = np.where(shadow, -1, np.arange(width)[None, :])
    left = np.maximum.accumulate(index, axis=1)  # last unshadowed column at or before each column
    right = np.minimum.accumulate(np.where(index < 0, width, index)[:, ::-1], axis=1)[:, ::-1]
    inside = (left[rows, cols] >= 0) & (right[rows, cols] < width)
    assert inside.mean() > 0.95
    r, lc, rc = rows[inside], left[rows, cols][inside], right[rows, cols][inside]
    nearer = depth[r, rc] < depth[r, lc] - 0.01
    assert nearer.mean() > 0.95, nearer.mean()
    assert (truth.labels[r, rc] >= 0).mean() > 0.9  # the nearer surface is an object
    # Wider baseline, wider shadow; none from the camera itself.
    assert sensors.occlusion_shadow(scene, config, truth, baseline=0.12).sum() > 1.3 * shadow.sum()
    assert not sensors.occlusion_shadow(scene, config, truth, baseline=0.0).any()
    # A flat table casts (almost) no shadow.
    flat = camera.observe(table_only, config)
    assert sensors.occlusion_shadow(table_only, config, flat, baseline=0.12).sum() <= 0.001 * (flat.depth > 0).sum()
    # The sensed image has no depth on most of the band (lateral noise may refill its rim).
    sensed = sensors.sense(scene, config, "kinect", seed=0)
    assert (sensed.depth[shadow] == 0).mean() > 0.8


def test_flying_pixels_only_at_discontinuities(scene):
    truth = camera.observe(scene, camera.CameraConfig(width=320, height=240)).depth.astype(np.float64)
    edges = sensors.discontinuities(truth, 0.02)
    assert edges.sum() > 100
    out = sensors.flying_pixels(truth, 1.0, 0.02, np.random.default_rng(0))
    changed = out != truth
    assert not (changed & ~edges).any() and changed.sum() > 0.99 * edges.sum()
    # Between the foreground and the background depth around the pixel.
    cross = ndimage.generate_binary_structure(2, 1)
    window_min = ndimage.minimum_filter(np.where(truth > 0, truth, np.inf), footprint=cross)
    window_max = ndimage.maximum_filter(truth, footprint=cross)
    assert (out[changed] >= window_min[changed]).all() and (out[changed] <= window_max[changed]).all()
    some = sensors.flying_pixels(truth, 0.3, 0.02, np.random.default_rng(1)) != truth
    assert 0.25 < some.sum() / edges.sum() < 0.35
    assert not (sensors.flying_pixels(truth, 0.0, 0.02, np.random.default_rng(1)) != truth).any()


def test_sensed_depth_departs_from_truth_only_near_edges(scene):
    """Beyond the axial noise, every effect but dropout acts at discontinuities: pixels with depth whose
    error is far outside the axial noise lie within a few pixels of a depth edge of the exact image."""
    truth = camera.observe(scene, SMALL).depth.astype(np.float64)
    edges = sensors.discontinuities(truth, 0.02) | ((truth == 0) & ndimage.binary_dilation(truth > 0))
    near = ndimage.binary_dilation(edges, iterations=4)
    for name in NOISY:
        sensed = sensors.sense(scene, SMALL, name, seed=0).depth
        sigma = sensors.axial_sigma(sensors.get_sensor(name), truth)
        wild = (sensed > 0) & (np.abs(sensed - truth) > 6 * sigma + 0.002)
        assert wild.sum() > 10, name  # flying pixels, jagged edges
        assert not (wild & ~near).any(), name


def test_lateral_noise_and_fattening_move_edges_not_surfaces():
    # A 4 cm step: left half at 0.6 m, right half a tilted plane at 0.8-0.82 m.
    depth = np.full((60, 80), 0.6)
    depth[:, 40:] = 0.8 + np.linspace(0, 0.02, 40)[None, :]
    out = sensors.lateral_noise(depth, 1.0, 0.02, np.random.default_rng(0))
    moved = out != depth
    assert moved.any() and (np.nonzero(moved)[1] >= 35).all() and (np.nonzero(moved)[1] < 45).all()
    assert set(np.unique(out[moved])) <= set(np.unique(depth))  # a neighbour's depth, nothing new
    fat = sensors.fatten_edges(depth, 3, 0.02)
    np.testing.assert_array_equal(fat[:, 40:43], 0.6)  # the nearer surface spreads 3 px
    np.testing.assert_array_equal(fat[:, 43:], depth[:, 43:])
    np.testing.assert_array_equal(fat[:, :40], depth[:, :40])


def test_dropout_fraction_as_configured():
    depth = np.full((1000, 1000), 0.7)
    rng = np.random.default_rng(0)
    lost = sensors.dropout(depth, 0.05, 0.0, 0.0, rng) == 0
    assert abs(lost.mean() - 0.05) < 0.002
    blobs = sensors.dropout(depth, 0.0, 0.03, 5.0, rng) == 0
    assert abs(blobs.mean() - 0.03) < 0.004  # ~370 discs
    # Blobs are discs: the lost pixels come in connected pieces of up to 81 pixels (radius 5).
    _, count = ndimage.label(blobs)
    assert blobs.sum() / count > 40
    both = sensors.dropout(depth, 0.05, 0.03, 5.0, rng) == 0
    assert abs(both.mean() - (1 - 0.95 * 0.97)) < 0.005
    assert (sensors.dropout(depth, 0.0, 0.0, 0.0, rng) == depth).all()


def test_dropout_on_a_sensed_table(table_only):
    sensor = sensors.get_sensor("stereo")
    sensed = sensors.sense(table_only, SMALL, sensor, seed=0)
    keep = _interior_table(sensed.truth, 3)
    lost = (sensed.depth[keep] == 0).mean()
    expected = 1 - (1 - sensor.dropout) * (1 - sensor.blob_dropout)
    assert abs(lost - expected) < 0.3 * expected, (lost, expected)  # a few dozen blobs on a small image


def test_quantisation_steps():
    z = np.linspace(0.5, 3.0, 20001)
    kinect = sensors.get_sensor("kinect")
    fb = kinect.focal_px * kinect.baseline
    disparity_only = sensors.quantise(z, kinect.focal_px, kinect.baseline, 1 / 8, 0.0)
    steps = fb / disparity_only / (1 / 8)
    np.testing.assert_allclose(steps, np.rint(steps), atol=1e-6)  # disparities on the 1/8 px lattice
    levels = np.unique(disparity_only)
    gaps = np.diff(levels)
    mid = 0.5 * (levels[1:] + levels[:-1])
    np.testing.assert_allclose(gaps, sensors.depth_step(kinect, mid), rtol=0.01)  # z^2 / (8 f b): 11.5 mm at 2 m
    assert abs(np.interp(2.0, mid, gaps) - 4 / (8 * fb)) < 2e-4
    # As the 16-bit stream delivers it: whole millimetres, disparity within half a millimetre's worth.
    out = sensors.quantise(z, kinect.focal_px, kinect.baseline, 1 / 8, 0.001)
    np.testing.assert_allclose(out * 1000, np.rint(out * 1000), atol=1e-6)
    assert np.abs(out - disparity_only).max() <= 0.0005 + 1e-9
    # RealSense at 0.7 m: the 1/32 px disparity step (0.8 mm) is below the 1 mm unit: millimetre steps.
    realsense = sensors.get_sensor("realsense")
    near = sensors.quantise(np.linspace(0.6, 0.8, 5001), realsense.focal_px, realsense.baseline, 1 / 32, 0.001)
    assert np.allclose(np.diff(np.unique(near)), 0.001, atol=2e-4)
    # No depth stays no depth.
    assert sensors.quantise(np.array([0.0, -1.0]), kinect.focal_px, kinect.baseline, 1 / 8, 0.001).tolist() == [0, 0]


def test_sensed_images_are_in_millimetres(scene):
    for name in NOISY:
        depth = sensors.sense(scene, SMALL, name, seed=2).depth.astype(np.float64)
        np.testing.assert_allclose(depth * 1000, np.rint(depth * 1000), atol=1e-3)


def test_unknown_sensor_names_the_choices(scene):
    with pytest.raises(ValueError, match="exact, kinect, realsense, stereo"):
        sensors.get_sensor("kinect_v2")
    with pytest.raises(ValueError, match="exact, kinect, realsense, stereo"):
        sensors.sense(scene, SMALL, "lidar")
    assert sorted(sensors.SENSORS) == ["exact", "kinect", "realsense", "stereo"]
    with pytest.raises(ValueError, match="noise=None"):
        sensors.sense(scene, camera.CameraConfig(width=16, height=12, noise=camera.DepthNoise()), "kinect")
    with pytest.raises(ValueError, match="dropout"):
        sensors.SensorModel("bad", dropout=1.0)
    with pytest.raises(ValueError, match="baseline"):
        sensors.SensorModel("bad", focal_px=500.0, axial="disparity", disparity_sigma=0.1)


# ---------------------------------------------------------------------------------------------
# Surroundings (SceneConfig.surroundings).


def _geoms(model: mujoco.MjModel) -> list[str]:
    return [mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_GEOM, i) for i in range(model.ngeom)]


def test_surroundings_are_seen_as_other_and_change_no_physics(objects):
    assets = [objects["tiny/box_a"], objects["tiny/cylinder"], objects["tiny/hex_prism"]]
    plain = scene_lib.make_scene(assets, 3, seed=1)
    dressed = scene_lib.make_scene(assets, 3, seed=1, config=scene_lib.SceneConfig(surroundings=True))
    # Physics untouched: the same settled state bit for bit, the same contact-capable geoms.
    np.testing.assert_array_equal(dressed.state, plain.state)
    np.testing.assert_array_equal(dressed.present, plain.present)
    names_plain, names_dressed = _geoms(plain.model), _geoms(dressed.model)
    assert names_dressed == [*names_plain[:1], *scene_lib.SURROUNDINGS_GEOMS, *names_plain[1:]]
    extra = np.isin(names_dressed, scene_lib.SURROUNDINGS_GEOMS)

    def contact_geoms(model, keep):
        capable = keep & ((model.geom_contype != 0) | (model.geom_conaffinity != 0))
        return [(n, model.geom_type[i], *model.geom_size[i], *model.geom_pos[i], *model.geom_friction[i])
                for i, n in enumerate(_geoms(model)) if capable[i]]

    assert contact_geoms(dressed.model, ~extra) == contact_geoms(plain.model, np.ones(plain.model.ngeom, bool))
    assert not (dressed.model.geom_contype[extra] | dressed.model.geom_conaffinity[extra]).any()
    assert (dressed.model.geom_group[extra] == scene_lib.VISUAL_GROUP).all()
    assert (dressed.geom_object()[extra] == scene_lib.OTHER).all()
    assert dressed.model.nq == plain.model.nq and dressed.model.nbody == plain.model.nbody
    # The default camera sees the stand (beside the table's +x edge, above the table top) and the wall.
    seen = camera.observe(dressed)
    other = seen.points[seen.point_labels == scene_lib.OTHER]
    half = 0.5 * dressed.config.table_size
    stand = (other[:, 0] > half + 0.01) & (other[:, 2] > 0.01)
    wall = other[:, 1] > half + 0.09
    assert stand.sum() > 1000 and wall.sum() > 10000
    assert (seen.labels == camera.NO_RETURN).sum() < (camera.observe(plain).labels == camera.NO_RETURN).sum()
    # Objects and the table look the same as without surroundings.
    bare = camera.observe(plain)
    mask = seen.labels != scene_lib.OTHER
    np.testing.assert_array_equal(seen.depth[mask], bare.depth[mask])
    np.testing.assert_array_equal(seen.labels[mask], bare.labels[mask])


def test_default_scene_has_no_surroundings(objects):
    assert scene_lib.SceneConfig().surroundings is False
    scene = scene_lib.make_scene([objects["tiny/box_a"]], 1, seed=0)
    assert not set(scene_lib.SURROUNDINGS_GEOMS) & set(_geoms(scene.model))
    labels = camera.observe(scene, SMALL).labels
    assert not (labels == scene_lib.OTHER).any()  # nothing but the table and objects in view
