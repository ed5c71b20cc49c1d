"""instrument.vision against synthetic crosses of known truth (tests/synthetic_cross.py).

Tolerances come from the physics, not from a lucky run: one section's centre scatters by about
the Cramér–Rao bound σn/A·sqrt(2σ/√π) (0.015 px for σ = 2, A = 200, σn = 2); a line through N such
centres over a length L is then known to ~CRB/√N in offset and ~CRB·√12/(L·√N) in angle. The
image tests allow ≥ 8 of those standard errors (with the crossing extrapolated from one side, the
centre error grows at most ~2×), so they cannot flake, yet a convention error (a half pixel, a sign,
a swapped axis) or a bias of a few hundredths of a pixel fails them.
"""

import numpy as np
import pytest

from instrument.vision import (
    CrossMeasurement,
    CrossNotFound,
    find_stripes,
    fit_line_bisquare,
    igcf_centers,
    locate_cross,
)
from tests.synthetic_cross import cramer_rao, render_cross, section_profiles

SHAPE = (240, 320)  # rows, cols


def _tolerances(m: CrossMeasurement, sigma=2.0, amplitude=200.0, noise=2.0, margin=8.0):
    """Centre (px) and angle (rad) tolerances: ``margin`` standard errors of the line fits."""
    per_section = 1.15 * cramer_rao(sigma, amplitude, noise)
    n = min(m.horizontal.sections, m.vertical.sections)
    length = n  # sections are one pixel apart
    centre = margin * 2.0 * per_section / np.sqrt(n)
    angle = margin * per_section * np.sqrt(12.0) / (length * np.sqrt(n))
    return centre, angle


CASES = {
    "axis-aligned": dict(),
    "rotated +0.3": dict(angle=0.3, center=(171.4, 112.6)),
    "rotated -0.3": dict(angle=-0.3, center=(150.9, 131.2)),
    "rotated +30°": dict(angle=np.radians(30.0), center=(160.5, 120.5), shape=(400, 400)),
    "rotated -30°": dict(angle=np.radians(-30.0), center=(190.25, 210.75), shape=(400, 400)),
    "non-perpendicular +3°": dict(angle=0.1, perpendicularity=np.radians(3.0), center=(140.3, 100.8)),
    "non-perpendicular -4°": dict(angle=-0.05, perpendicularity=np.radians(-4.0), center=(180.6, 140.1)),
    "near left edge": dict(angle=0.05, center=(6.3, 120.4)),
    "near top-right corner": dict(angle=-0.08, center=(290.7, 22.2)),
    "near bottom edge": dict(angle=0.2, center=(160.1, 231.9)),
    "saturated": dict(angle=0.15, amplitude=600.0, center=(155.5, 125.5)),
    "12-bit": dict(angle=-0.12, dtype=np.uint16, saturation=4095, amplitude=3200.0, background=150.0,
                   noise=32.0, center=(162.2, 118.9)),
    "12-bit saturated": dict(angle=0.22, dtype=np.uint16, saturation=4095, amplitude=9000.0,
                             background=150.0, noise=32.0, center=(148.4, 126.6)),
    "10-bit": dict(angle=0.18, dtype=np.uint16, saturation=1023, amplitude=800.0, background=40.0,
                   noise=8.0, center=(151.9, 129.4)),
    "16-bit": dict(angle=0.07, dtype=np.uint16, saturation=65535, amplitude=40000.0, background=900.0,
                   noise=400.0, center=(166.6, 113.3)),
    "wide stripe": dict(angle=0.1, sigma=3.5, center=(158.0, 121.0)),
    "dim vertical stripe": dict(angle=0.2, vertical_amplitude=70.0, center=(150.2, 118.3)),
    "background gradient": dict(angle=-0.25, background=30.0, amplitude=180.0,
                                background_gradient=(0.15, -0.1), center=(170.7, 125.4)),
    "narrow stripe": dict(angle=-0.2, sigma=1.1, center=(161.1, 117.7)),
}


@pytest.mark.parametrize("name", sorted(CASES))
def test_centre_and_angle_match_truth(name):
    kwargs = dict(CASES[name])
    kwargs.setdefault("shape", SHAPE)
    img, truth = render_cross(seed=sum(map(ord, name)), **kwargs)
    saturation = kwargs.get("saturation", 255)
    m = locate_cross(img, saturation=None if saturation in (255, 65535) else saturation)
    amplitude, noise = kwargs.get("amplitude", 200.0), kwargs.get("noise", 2.0)
    # above saturation the flanks carry the information: judge by the unsaturated-equivalent bound
    effective_amplitude = min(amplitude, saturation - kwargs.get("background", 10.0))
    effective_amplitude = min(effective_amplitude, kwargs.get("vertical_amplitude") or np.inf)
    tol_centre, tol_angle = _tolerances(m, kwargs.get("sigma", 2.0), effective_amplitude, noise)
    if kwargs.get("sigma", 2.0) > 3.0:  # the 9-px window covers only ±1.3σ: allow its precision loss
        tol_centre, tol_angle = 1.5 * tol_centre, 1.5 * tol_angle
    assert np.hypot(*(m.center - truth.center)) < tol_centre, (m.center, truth.center, tol_centre)
    assert abs(m.angle - truth.angle) < tol_angle, (m.angle, truth.angle, tol_angle)
    assert abs(m.perpendicularity - truth.perpendicularity) < 2 * tol_angle
    # quality figures
    assert m.horizontal.sections >= 100 and m.vertical.sections >= 100
    per_section = 1.15 * cramer_rao(kwargs.get("sigma", 2.0), effective_amplitude, noise)
    assert m.horizontal.residual_rms < 3 * per_section + 0.01
    if amplitude + kwargs.get("background", 10.0) > saturation * 1.2:
        assert m.horizontal.saturated_sections > 0.9 * m.horizontal.sections
        assert m.peak_level == saturation
    else:
        assert m.horizontal.saturated_sections == 0
        assert m.peak_level < saturation


def test_stripe_lines_follow_the_conventions():
    """Directions point to +x / +y, points lie on the true lines, φh and φv measured separately."""
    phi_h, phi_v = 0.20, 0.26
    img, truth = render_cross(SHAPE, (150.0, 110.0), 0.5 * (phi_h + phi_v), phi_v - phi_h, seed=3)
    m = locate_cross(img)
    dh, dv = m.horizontal.direction, m.vertical.direction
    assert dh[0] > 0 and dv[1] > 0
    assert np.isclose(np.linalg.norm(dh), 1.0) and np.isclose(np.linalg.norm(dv), 1.0)
    assert np.arctan2(dh[1], dh[0]) == pytest.approx(phi_h, abs=2e-4)
    assert np.arctan2(-dv[0], dv[1]) == pytest.approx(phi_v, abs=2e-4)
    # the reported points lie on the true centre lines
    nh = np.array([-np.sin(phi_h), np.cos(phi_h)])
    nv = np.array([np.cos(phi_v), np.sin(phi_v)])
    assert abs(nh @ (m.horizontal.point - truth.center)) < 0.01
    assert abs(nv @ (m.vertical.point - truth.center)) < 0.01


def test_downsampled_detection_on_a_camera_sized_frame():
    """A 1040×1024 frame goes through the block-averaged path (factor 4) and stays sub-0.01 px."""
    img, truth = render_cross((1040, 1024), (503.3, 488.8), 0.25, 0.01, seed=11)
    m = locate_cross(img)
    assert find_stripes(img, 255).factor == 4
    assert np.hypot(*(m.center - truth.center)) < 0.01
    assert abs(m.angle - truth.angle) < 2e-5
    assert m.horizontal.sections > 900 and m.vertical.sections > 900


# --- IGCF on single cross-sections -------------------------------------------------------------


def test_igcf_precision_reaches_the_cramer_rao_bound():
    """Seeded Monte-Carlo: the I²-weighted fit is within 15 % of the CRB (sampling error ~1 %)."""
    sigma, amplitude, noise = 2.0, 200.0, 2.0
    profiles, truth = section_profiles(4000, sigma=sigma, amplitude=amplitude, noise=noise, seed=7)
    r = igcf_centers(profiles, axis=0, background=10.0, saturation=255)
    assert r.valid.all() and not r.saturated.any()
    error = r.center - truth
    crb = cramer_rao(sigma, amplitude, noise)
    assert crb == pytest.approx(0.0150, abs=1e-4)  # method.md's worked figure
    ratio = np.std(error) / crb
    assert 0.9 < ratio < 1.15, ratio  # never better than the bound, at most 15 % worse
    assert abs(np.mean(error)) < 4 * crb / np.sqrt(len(error))


@pytest.mark.parametrize("amplitude", [400.0, 1000.0])
def test_igcf_unbiased_on_saturated_profiles(amplitude):
    # noise-free and unquantised: the fit of the flanks is exact to the pixel integration's 1e-4
    clean, truth = section_profiles(2000, amplitude=amplitude, noise=0.0, seed=1, quantize=False)
    r = igcf_centers(clean, axis=0, background=10.0, saturation=255)
    assert r.valid.all() and r.saturated.all()
    assert np.max(np.abs(r.center - truth)) < 2e-4
    # noisy: mean error (bias) below 0.002 px, far above its 4-standard-error sampling noise
    noisy, truth = section_profiles(4000, amplitude=amplitude, noise=2.0, seed=2)
    r = igcf_centers(noisy, axis=0, background=10.0, saturation=255)
    error = r.center[r.valid] - truth[r.valid]
    assert r.valid.mean() > 0.99
    assert abs(error.mean()) < 0.002
    assert abs(error.mean()) < 4 * error.std() / np.sqrt(len(error)) + 2e-4


def test_single_saturated_pixel_stays_in_the_fit():
    """One clipped pixel: the section is not flagged and its centre is still found (slightly off)."""
    offsets = np.arange(25) - 12.0
    profile = 10.0 + 250.0 * np.exp(-0.5 * (offsets / 2.0) ** 2)  # only the centre pixel > 255
    clipped = np.minimum(profile, 255.0)
    assert (clipped >= 255).sum() == 1
    r = igcf_centers(clipped[None, :], background=10.0, saturation=255)
    assert r.valid[0] and not r.saturated[0]
    assert r.center[0] == pytest.approx(12.0, abs=1e-6)  # symmetric: the clip cannot move it
    # shifted by a third of a pixel, the kept clipped pixel biases the centre a little, as accepted
    profile = 10.0 + 250.0 * np.exp(-0.5 * ((offsets - 0.3) / 2.0) ** 2)
    r = igcf_centers(np.minimum(profile, 255.0)[None, :], background=10.0, saturation=255)
    assert not r.saturated[0] and abs(r.center[0] - 12.3) < 0.05


def test_igcf_rejects_what_cannot_be_fitted():
    length = 25
    t = np.arange(length, dtype=float)
    good = 10 + 200 * np.exp(-0.5 * ((t - 12.2) / 2) ** 2)
    flat = np.full(length, 60.0)  # a2 = 0: no peak
    edge = 10 + 200 * np.exp(-0.5 * ((t - 0.0) / 2) ** 2)  # brightest pixel on the profile's end
    spike = np.full(length, 10.0)
    spike[12] = 200.0  # fewer than 3 pixels above background
    weak = 10 + 5 * np.exp(-0.5 * ((t - 12.0) / 2) ** 2)
    r = igcf_centers(np.stack([good, flat, edge, spike, weak]), background=10.0, min_amplitude=20.0)
    assert r.valid.tolist() == [True, False, False, False, False]
    assert np.isnan(r.center[1:]).all()
    assert r.center[0] == pytest.approx(12.2, abs=1e-3)


def test_igcf_axis_and_per_section_background():
    profiles, truth = section_profiles(50, noise=0.0, quantize=False, seed=4)  # (length, n)
    shifted = profiles + np.linspace(0, 30, 50)[None, :]
    a = igcf_centers(shifted, axis=0, background=10.0 + np.linspace(0, 30, 50))
    b = igcf_centers(shifted.T, axis=1, background=10.0 + np.linspace(0, 30, 50))
    np.testing.assert_allclose(a.center, truth, atol=2e-4)
    np.testing.assert_array_equal(a.center, b.center)


# --- bisquare line fit --------------------------------------------------------------------------


def test_bisquare_line_fit_ignores_outliers():
    rng = np.random.default_rng(5)
    x = np.arange(400.0)
    y = 3.0 + 0.1 * x + rng.normal(0, 0.02, x.size)
    bad = rng.choice(x.size, 60, replace=False)
    y[bad] += rng.uniform(2, 20, bad.size)  # 15 % gross outliers, all on one side
    fit = fit_line_bisquare(np.column_stack([x, y]))
    assert fit.converged
    assert fit.intercept == pytest.approx(3.0, abs=0.01) and fit.slope == pytest.approx(0.1, abs=5e-5)
    assert np.all(fit.weights[bad] == 0)
    assert fit.residual_rms == pytest.approx(0.02 / np.hypot(1, 0.1), rel=0.2)
    ols = np.polyfit(x, y, 1)
    assert abs(ols[1] - 3.0) > 0.5  # ordinary least squares is dragged away


def test_bisquare_fit_of_x_as_function_of_y():
    y = np.arange(100.0)
    x = 50.0 - 0.2 * y
    fit = fit_line_bisquare(np.column_stack([x, y]), independent=1)
    assert fit.intercept == pytest.approx(50.0) and fit.slope == pytest.approx(-0.2)
    assert fit.residual_rms < 1e-9
    with pytest.raises(ValueError, match="at least two"):
        fit_line_bisquare([[1.0, 2.0]])
    with pytest.raises(ValueError, match="degenerate"):
        fit_line_bisquare([[1.0, 2.0], [1.0, 3.0]])


# --- thresholds ---------------------------------------------------------------------------------


@pytest.mark.parametrize("threshold", ["otsu", 60.0])
def test_threshold_choices_find_the_same_cross(threshold):
    img, truth = render_cross(SHAPE, (150.5, 120.5), 0.1, seed=9)
    a = locate_cross(img)
    b = locate_cross(img, threshold=threshold)
    np.testing.assert_allclose(a.center, b.center, atol=1e-3)
    assert np.hypot(*(b.center - truth.center)) < 0.02


# --- failures -----------------------------------------------------------------------------------


def test_no_cross():
    img, _ = render_cross(SHAPE, horizontal=False, vertical=False, seed=1)
    with pytest.raises(CrossNotFound, match="no cross"):
        locate_cross(img)


def test_dark_frame():
    with pytest.raises(CrossNotFound, match="no cross"):
        locate_cross(np.zeros(SHAPE, np.uint8))


@pytest.mark.parametrize("keep", ["horizontal", "vertical"])
def test_only_one_stripe(keep):
    img, _ = render_cross(SHAPE, (150.0, 120.0), 0.1, horizontal=keep == "horizontal",
                          vertical=keep == "vertical", seed=2)
    with pytest.raises(CrossNotFound, match=f"only one stripe found \\(near-{keep}\\)"):
        locate_cross(img)


def test_two_crosses():
    img, _ = render_cross((300, 400), (110.0, 90.0), 0.05, extra_crosses=[((290.0, 210.0), 0.05)], seed=4)
    with pytest.raises(CrossNotFound, match="more than one cross"):
        locate_cross(img)


def test_stripe_too_short():
    # a 60-px vertical stub centred on the crossing: only a few sections outside the crossing zone
    img, _ = render_cross(SHAPE, (150.0, 120.0), 0.0, v_extent=(90.0, 150.0), seed=5)
    with pytest.raises(CrossNotFound, match="near-vertical stripe too short to fit"):
        locate_cross(img)


def test_bad_input_types_and_shapes():
    img, _ = render_cross(SHAPE, seed=6)
    with pytest.raises(TypeError, match="uint8 or uint16"):
        locate_cross(img.astype(np.float32))
    with pytest.raises(TypeError, match="uint8 or uint16"):
        locate_cross(img.astype(np.int32))
    with pytest.raises(TypeError, match="numpy array"):
        locate_cross(img.tolist())
    with pytest.raises(ValueError, match="2-D.*colour"):
        locate_cross(np.dstack([img, img, img]))
    with pytest.raises(ValueError, match="2-D"):
        locate_cross(img.ravel())
    with pytest.raises(ValueError, match="too small"):
        locate_cross(img[:8, :8])
    with pytest.raises(ValueError, match="saturation"):
        locate_cross(img, saturation=4095)
    with pytest.raises(ValueError, match="threshold"):
        locate_cross(img, threshold="triangle")


def test_non_contiguous_view_is_accepted():
    img, truth = render_cross((240, 640), (160.3, 120.2), 0.1, seed=8)
    view = img[:, ::2]  # every second column: the cross in a strided view
    m = locate_cross(view)
    assert m.center == pytest.approx([truth.center[0] / 2, truth.center[1]], abs=0.05)


def test_hot_pixels_and_a_reflection_do_not_disturb():
    import cv2

    rng = np.random.default_rng(12)
    img, truth = render_cross(SHAPE, (150.3, 120.7), 0.1, seed=13)
    img[rng.integers(0, SHAPE[0], 40), rng.integers(0, SHAPE[1], 40)] = 255  # hot pixels
    cv2.circle(img, (265, 45), 12, 255, -1)  # a saturated reflection
    m = locate_cross(img)
    assert np.hypot(*(m.center - truth.center)) < 0.02
    assert abs(m.angle - truth.angle) < 2e-4
    # hot pixels alone are no cross
    blank, _ = render_cross(SHAPE, horizontal=False, vertical=False, seed=14)
    blank[rng.integers(0, SHAPE[0], 40), rng.integers(0, SHAPE[1], 40)] = 255
    with pytest.raises(CrossNotFound, match="no cross"):
        locate_cross(blank)


@pytest.mark.parametrize("seed", range(8))
def test_random_crosses(seed):
    """Seeded random geometry: any angle within ±0.45 rad, a few degrees off square, anywhere."""
    rng = np.random.default_rng(1000 + seed)
    rows, cols = SHAPE
    center = (rng.uniform(0.15, 0.85) * cols, rng.uniform(0.15, 0.85) * rows)
    angle, perpendicularity = rng.uniform(-0.45, 0.45), rng.uniform(-0.06, 0.06)
    sigma, amplitude = rng.uniform(1.2, 3.0), rng.uniform(80.0, 230.0)
    img, truth = render_cross(SHAPE, center, angle, perpendicularity, sigma=sigma, amplitude=amplitude,
                              seed=seed)
    m = locate_cross(img)
    tol_centre, tol_angle = _tolerances(m, sigma, amplitude, 2.0)
    assert np.hypot(*(m.center - truth.center)) < tol_centre
    assert abs(m.angle - truth.angle) < tol_angle
    assert abs(m.perpendicularity - truth.perpendicularity) < 2 * tol_angle
