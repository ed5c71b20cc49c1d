"""The renderer against the analytic truth: stripe centre lines, width, noise, saturation, depth."""

import time

import numpy as np
import pytest

from sim_devices._transforms import euler_to_matrix, make_transform
from sim_devices.camera import AXIS_NAMES, OpticalBench, Renderer
from sim_devices.world import World, WorldConfig

POSES = [
    make_transform(np.eye(3), [0.0, 0.0, 0.0]),
    make_transform(euler_to_matrix(*np.radians([0.6, -0.4, 0.9])), [0.030, 0.050, 0.020]),
    make_transform(euler_to_matrix(*np.radians([-1.0, 0.8, -0.7])), [0.065, 0.010, 0.060]),
]


@pytest.fixture(scope="module")
def bench():
    return OpticalBench(World(WorldConfig(seed=11)))


def analytic_stripe_curves(bench, name, opr_in_m):
    """Each fan's stripe as image points: the fan plane ∩ the screen plane as a 3-D line (its
    direction is the cross product of the normals), projected on the screen, imaged by the true
    camera. Derived here independently of the renderer's 2-D line formula."""
    screen, emitter, camera = bench.screens[name], bench.emitters[name], bench.cameras[name]
    rotation, translation = opr_in_m[:3, :3], opr_in_m[:3, 3]
    fan_point = rotation @ emitter.offset + translation
    curves = []
    for normal_o in emitter.fan_normals.values():
        n = rotation @ normal_o
        direction = np.cross(n, screen.normal)
        direction /= np.linalg.norm(direction)
        # The point of the 3-D line closest to the screen origin: solve n·x = n·p, N·x = N·o, d·x = d·o.
        a = np.array([n, screen.normal, direction])
        b = np.array([n @ fan_point, screen.normal @ screen.origin, direction @ screen.origin])
        on_line = np.linalg.solve(a, b)
        s = np.linspace(-0.25, 0.25, 4001)
        points = on_line + s[:, None] * direction
        uv = np.stack([(points - screen.origin) @ screen.u, (points - screen.origin) @ screen.v], -1)
        curves.append(camera.screen_to_pixel(uv))
    return curves


def centroid_errors(signal, curve, other, margin=40, half=14):
    """Per-section weighted centroid across the stripe minus the analytic centre, in px."""
    height, width = signal.shape
    along_x = np.ptp(curve[:, 0]) >= np.ptp(curve[:, 1])
    lead, cross = (curve[:, 0], curve[:, 1]) if along_x else (curve[:, 1], curve[:, 0])
    order = np.argsort(lead)
    lead, cross = lead[order], cross[order]
    other_lead, other_cross = (other[:, 1], other[:, 0]) if along_x else (other[:, 0], other[:, 1])
    o = np.argsort(other_lead)
    errors = []
    size_lead, size_cross = (width, height) if along_x else (height, width)
    for k in range(20, size_lead - 20):
        centre = np.interp(k, lead, cross)
        if not (half + 2 < centre < size_cross - half - 3):
            continue
        # skip the zone where the other stripe crosses this section
        if abs(k - np.interp(centre, other_lead[o], other_cross[o])) < margin:
            continue
        idx = np.arange(int(round(centre)) - half, int(round(centre)) + half + 1)
        profile = signal[idx, k] if along_x else signal[k, idx]
        errors.append((profile @ idx) / profile.sum() - centre)
    return np.array(errors)


@pytest.mark.parametrize("pose_index", range(len(POSES)))
def test_noise_free_stripe_centres_match_the_analytic_intersection(bench, pose_index):
    renderer = Renderer(bench)
    pose = POSES[pose_index]
    for name in AXIS_NAMES:
        image = renderer.render(name, pose, noise=False, quantise=False)
        background = renderer.render(name, pose, noise=False, quantise=False, exposure_scale=0.0)
        signal = (image - background).astype(float)
        curves = analytic_stripe_curves(bench, name, pose)
        assert len(curves) == 2
        for i in range(2):
            errors = centroid_errors(signal, curves[i], curves[1 - i])
            assert len(errors) > 700, f"camera {name}: stripe {i} mostly off the image"
            assert np.abs(errors).max() < 0.01, (
                f"camera {name} stripe {i}: max centre error {np.abs(errors).max():.4f} px"
            )


def test_stripe_width_is_about_two_pixels(bench):
    renderer = Renderer(bench)
    name = "x"
    image = renderer.render(name, POSES[0], noise=False, quantise=False)
    signal = (image - renderer.render(name, POSES[0], noise=False, quantise=False, exposure_scale=0.0)).astype(float)
    curve = analytic_stripe_curves(bench, name, POSES[0])[0]
    along_x = np.ptp(curve[:, 0]) >= np.ptp(curve[:, 1])
    k = 200
    lead, cross = (curve[:, 0], curve[:, 1]) if along_x else (curve[:, 1], curve[:, 0])
    centre = np.interp(k, *(np.sort(lead), cross[np.argsort(lead)]))
    idx = np.arange(int(round(centre)) - 14, int(round(centre)) + 15)
    profile = signal[idx, k] if along_x else signal[k, idx]
    variance = profile @ (idx - centre) ** 2 / profile.sum() - 1.0 / 12.0  # minus the pixel box
    assert 1.6 < np.sqrt(variance) < 2.5


def test_noise_is_seeded_per_frame_and_the_sensor_saturates(bench):
    renderer = Renderer(bench, seed=4)
    a = renderer.render("y", POSES[1], seq=7)
    b = renderer.render("y", POSES[1], seq=7)
    c = renderer.render("y", POSES[1], seq=8)
    assert a.dtype == np.uint8 and a.shape == (1040, 1024)
    np.testing.assert_array_equal(a, b)
    assert np.any(a != c)
    assert a.max() == 255  # the crossing of the two stripes saturates
    corner = a[:200, :200].astype(float)  # background: level ≈ 5 with read + shot noise
    cfg = bench.config
    expected_sigma = np.sqrt(cfg.read_noise**2 + cfg.conversion_gain * cfg.background_level)
    assert 0.6 * expected_sigma < corner.std() < 1.6 * expected_sigma + 0.3


def test_twelve_bit_output_and_exposure(bench):
    renderer = Renderer(bench, bit_depth=12)
    image = renderer.render("z", POSES[2], seq=1)
    assert image.dtype == np.uint16 and image.max() == 4095
    dim = renderer.render("z", POSES[2], seq=1, exposure_scale=0.3)
    assert 600 < dim.max() < 4095  # the crossing no longer saturates


def test_pose_facing_away_gives_a_dark_frame(bench):
    away = make_transform(euler_to_matrix(0.0, 0.0, np.pi), [0.0, 0.0, 0.0])  # beam x points to −x
    image = Renderer(bench).render("x", away, seq=0)
    assert image.max() < 40


def test_three_megapixel_frames_render_well_under_a_second(bench):
    renderer = Renderer(bench)
    renderer.render_all(POSES[1], seq=0)  # warm the background cache
    start = time.perf_counter()
    renderer.render_all(POSES[1], seq=1)
    assert time.perf_counter() - start < 2.0  # ≈ 0.1 s idle; generous for a loaded 2-core machine
