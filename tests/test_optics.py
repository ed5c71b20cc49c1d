"""The optical bench: nominal geometry in the station-file format, true vs nominal differences."""

import json

import numpy as np
import pytest

from sim_devices.camera import AXIS_NAMES, OpticalBench, OpticsConfig
from sim_devices.world import World, WorldConfig

AXIS = {"x": 0, "y": 1, "z": 2}


@pytest.fixture(scope="module")
def bench():
    return OpticalBench(World(WorldConfig(seed=3)))


def _apply(h, xy):
    p = np.c_[np.atleast_2d(xy), np.ones(len(np.atleast_2d(xy)))] @ np.asarray(h).T
    return p[:, :2] / p[:, 2:]


def test_nominal_geometry_follows_the_station_contract(bench):
    geometry = bench.nominal_geometry()
    assert set(geometry) == {"screens"} and set(geometry["screens"]) == {"x", "y", "z"}
    for name, screen in geometry["screens"].items():
        e_k = np.eye(3)[AXIS[name]]
        u, v = np.array(screen["u"]), np.array(screen["v"])
        np.testing.assert_allclose(np.cross(u, v), e_k)  # rotation about k turns the cross positively
        np.testing.assert_allclose(screen["origin"], 0.25 * e_k)
        assert screen["size_px"] == [1024, 1040]
        h = np.array(screen["pixel_to_screen"])
        assert h.shape == (3, 3)
        # The image centre looks at (35, 35) mm; the view spans about −45…+115 mm each way.
        np.testing.assert_allclose(_apply(h, [511.5, 519.5])[0], [0.035, 0.035], atol=1e-12)
        corners = _apply(h, [[0, 0], [1023, 0], [0, 1039], [1023, 1039]])
        assert corners.min() < -0.040 and corners.max() > 0.110
        scale = np.sqrt(abs(np.linalg.det(h[:2, :2])))
        assert scale == pytest.approx(0.156e-3)
    dets = {n: np.linalg.det(np.array(s["pixel_to_screen"])[:2, :2]) for n, s in geometry["screens"].items()}
    assert any(d < 0 for d in dets.values()), "at least one camera sees its screen mirrored"
    turned = [n for n, s in geometry["screens"].items() if abs(np.array(s["pixel_to_screen"])[0, 0]) < 1e-12]
    assert turned, "at least one camera is mounted turned by 90°"


def test_true_optics_differ_from_nominal_by_realistic_amounts(bench):
    for name in AXIS_NAMES:
        true, nominal = bench.screens[name], bench.nominal_screens[name]
        assert 0 < np.linalg.norm(true.origin - nominal.origin) < 6e-3
        tilt = np.degrees(np.arccos(np.clip(true.normal @ nominal.normal, -1, 1)))
        assert 0 < tilt < 0.6
        camera = bench.cameras[name]
        nominal_h = bench.nominal_pixel_to_screen[name]
        ratio = np.sqrt(abs(np.linalg.det(camera.pixel_to_screen_h[:2, :2]) / np.linalg.det(nominal_h[:2, :2])))
        assert 0 < abs(ratio - 1) < 3e-3
        # radial distortion of a fraction of a pixel at the corners
        corner = np.array([0.0, 0.0])
        shift = np.linalg.norm(np.array(camera._distort(*corner)) - corner)
        assert 0.01 < shift < 1.5
        emitter = bench.emitters[name]
        beam_tilt = np.degrees(np.arccos(emitter.beam[AXIS[name]])) * 3600
        assert beam_tilt < 100  # arc-seconds
        n1, n2 = emitter.fan_normals.values()
        assert abs(np.degrees(np.arcsin(abs(n1 @ n2))) * 3600) < 120  # fans nearly perpendicular


def test_camera_model_round_trips(bench):
    rng = np.random.default_rng(0)
    pixels = rng.uniform([0, 0], [1023, 1039], (200, 2))
    for camera in bench.cameras.values():
        back = camera.screen_to_pixel(camera.pixel_to_screen(pixels))
        np.testing.assert_allclose(back, pixels, atol=1e-8)


def test_bench_is_reproducible_per_seed_and_described_in_json():
    a = OpticalBench(World(WorldConfig(seed=5))).true_description()
    b = OpticalBench(World(WorldConfig(seed=5))).true_description()
    c = OpticalBench(World(WorldConfig(seed=6))).true_description()
    assert json.dumps(a) == json.dumps(b)
    assert json.dumps(a) != json.dumps(c)


def test_config_rejects_unknown_fields_and_accepts_overrides():
    with pytest.raises(ValueError, match="unknown field"):
        OpticsConfig.from_dict({"screen_distanse": 0.3})
    bench = OpticalBench(World(), {"size_px": [2448, 2048], "cameras": {
        "x": {"mirrored": False, "turn_deg": 0}, "y": {"mirrored": True, "turn_deg": 270},
        "z": {"mirrored": True, "turn_deg": 180}}})
    assert bench.nominal_geometry()["screens"]["x"]["size_px"] == [2448, 2048]
