"""Screen geometry: loading, validation messages, round trip; and the realistic test station.

The station used by all pose tests: screens at 0.25 m, each camera imaging ~160 mm of screen onto
1024 × 1040 px (~0.156 mm/px), cameras mirrored and turned by arbitrary angles.
"""

import copy

import numpy as np
import pytest

from instrument.pose import Distortion, Geometry, GeometryError, make_homography

METRES_PER_PIXEL = 0.160 / 1024
SIZE_PX = [1024, 1040]
AXES = {
    "x": ([0.25, 0, 0], [0, 1, 0], [0, 0, 1]),
    "y": ([0, 0.25, 0], [0, 0, 1], [1, 0, 0]),
    "z": ([0, 0, 0.25], [1, 0, 0], [0, 1, 0]),
}


def station_dict(cameras=None, *, distortion=None, size=True):
    """Station geometry mapping; ``cameras`` maps screen → (rotation rad, mirrored, perspective)."""
    cameras = cameras or {"x": (0.0, False, (0, 0)), "y": (0.0, False, (0, 0)), "z": (0.0, False, (0, 0))}
    screens = {}
    for name, (origin, u, v) in AXES.items():
        rotation, mirrored, perspective = cameras[name]
        screen = {
            "origin": origin,
            "u": u,
            "v": v,
            "pixel_to_screen": make_homography(
                METRES_PER_PIXEL, rotation=rotation, mirrored=mirrored, perspective=perspective
            ).tolist(),
        }
        if size:
            screen["size_px"] = SIZE_PX
        if distortion and name in distortion:
            screen["distortion"] = distortion[name]
        screens[name] = screen
    return {"screens": screens}


# Mirrored, turned by odd angles, with a little perspective: the hard case for stripe matching.
AWKWARD_CAMERAS = {
    "x": (np.radians(37.0), True, (3e-5, -2e-5)),
    "y": (np.radians(-128.0), False, (-1e-5, 2e-5)),
    "z": (np.radians(90.0), True, (0.0, 1e-5)),
}


def test_round_trip_to_dict_from_dict():
    data = station_dict(AWKWARD_CAMERAS, distortion={"z": {"k1": 2e-9, "k2": -1e-16, "center_px": [510.0, 522.0]}})
    geometry = Geometry.from_dict(data)
    again = Geometry.from_dict(geometry.to_dict())
    assert again.to_dict() == geometry.to_dict()
    np.testing.assert_array_equal(
        again.screens["x"].pixel_to_screen, np.asarray(data["screens"]["x"]["pixel_to_screen"])
    )
    assert again.screens["z"].distortion == Distortion(2e-9, -1e-16, (510.0, 522.0))
    assert again.screens["y"].size_px == (1024, 1040)


def test_homography_scale_and_mirror():
    screen = Geometry.from_dict(station_dict(AWKWARD_CAMERAS)).screens["x"]
    corners = screen.pixels_to_screen([[0, 0], [1023, 0], [0, 1039]])
    assert np.linalg.norm(corners[1] - corners[0]) == pytest.approx(1023 * METRES_PER_PIXEL, rel=0.05)
    assert np.linalg.det(screen.pixel_to_screen) < 0  # mirrored camera
    back = screen.screen_to_pixels(corners)
    np.testing.assert_allclose(back, [[0, 0], [1023, 0], [0, 1039]], atol=1e-9)


def test_distortion_inverse():
    distortion = Distortion(3e-9, 2e-16, (500.0, 530.0))
    points = np.array([[0.0, 0.0], [1023.0, 1039.0], [500.0, 530.0], [700.0, 100.0]])
    np.testing.assert_allclose(distortion.undistort(distortion.distort(points)), points, atol=1e-9)
    # At the corner the correction is several pixels: the model matters.
    assert np.linalg.norm(distortion.undistort(points[:1]) - points[:1]) > 1.0


def _mutated(path, value):
    data = station_dict()
    node = data
    for key in path[:-1]:
        node = node[key]
    if value is KeyError:
        del node[path[-1]]
    else:
        node[path[-1]] = value
    return data


@pytest.mark.parametrize(
    "path, value, message",
    [
        (("screens", "y", "u"), [0, 0, 2], "screens.y.u: must be a unit vector"),
        (("screens", "x", "v"), [0, 0.6, 0.8], "screens.x.v: must be perpendicular to u"),
        (("screens", "z", "origin"), [0, 0, float("nan")], "screens.z.origin: must be finite"),
        (("screens", "z", "origin"), [0, 0], "screens.z.origin: expected 3 numbers"),
        (("screens", "x", "pixel_to_screen"), [[1, 0], [0, 1]], "screens.x.pixel_to_screen"),
        (("screens", "x", "pixel_to_screen"), [[1, 0, 0], [2, 0, 0], [0, 0, 1]], "singular homography"),
        (("screens", "y"), KeyError, "screens.y: missing"),
        (("screens", "y", "pixel_to_screen"), KeyError, "screens.y.pixel_to_screen: missing"),
        (("screens", "x", "colour"), "red", "screens.x: unknown field"),
        (("screens", "w"), {}, "unknown screen"),
        (("screens", "x", "u"), [0, 0, 1], "must point along +x"),  # u, v swapped: mirrored screen frame
        (("screens", "x", "origin"), [-0.25, 0, 0], "screens.x.origin"),
        (("screens", "x", "size_px"), [1024.5, 1040], "screens.x.size_px"),
        (("screens", "x", "distortion"), {"k1": 1e-9}, "screens.x.distortion.center_px: missing"),
        (("screens", "x", "distortion"), {"k3": 1.0, "center_px": [0, 0]}, "screens.x.distortion: unknown"),
    ],
)
def test_validation_names_the_field(path, value, message):
    data = _mutated(path, value)
    if path[-1] == "u" and value == [0, 0, 1]:
        data["screens"]["x"]["v"] = [0, 1, 0]
    with pytest.raises(GeometryError, match=message.replace("+", r"\+").replace(".", r"\.")):
        Geometry.from_dict(data)


def test_validation_of_top_level():
    with pytest.raises(GeometryError, match="screens: missing"):
        Geometry.from_dict({})
    with pytest.raises(GeometryError, match="screens: expected a mapping"):
        Geometry.from_dict({"screens": [1, 2, 3]})
    data = copy.deepcopy(station_dict())
    data["extra"] = 1
    with pytest.raises(GeometryError, match="unknown field"):
        Geometry.from_dict(data)
