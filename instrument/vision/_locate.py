"""``locate_cross``: one camera image → the sub-pixel cross (method.md §2).

Without a prior: coarse stripes on a block-averaged copy of the whole frame (``_detect``), then
the band → IGCF → bisquare pipeline (``_bands``). With a prior (the previous frame's result): the
stripes are re-acquired near the prior's lines only (``_track``) and the same pipeline runs; if the
prior is lost, the full search runs and the result says so.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import replace

import numpy as np

from instrument.vision._bands import CrossJob
from instrument.vision._detect import find_stripes
from instrument.vision._fine import PriorLost, measure_crosses
from instrument.vision._track import TRACK_SEARCH_PX, lost_after_fit, prior_lines
from instrument.vision._types import CrossMeasurement, CrossNotFound

MIN_SECTIONS = 30  # fewer usable cross-sections than this: the stripe is too short to fit
DEFAULT_SATURATION = {np.dtype(np.uint8): 255, np.dtype(np.uint16): 65535}
MIN_SIDE = 16


def _check_image(img, saturation):
    if not isinstance(img, np.ndarray):
        raise TypeError(f"image must be a numpy array, got {type(img).__name__}")
    if img.dtype not in DEFAULT_SATURATION:
        raise TypeError(f"image must be uint8 or uint16 greyscale, got dtype {img.dtype}")
    if img.ndim != 2:
        raise ValueError(
            f"image must be 2-D (rows, cols) greyscale, got shape {img.shape}"
            + (" — convert colour images to one channel first" if img.ndim == 3 else "")
        )
    if min(img.shape) < MIN_SIDE:
        raise ValueError(
            f"image is too small to hold a cross: shape {img.shape}, need ≥ {MIN_SIDE} px a side"
        )
    full_scale = DEFAULT_SATURATION[img.dtype]
    if saturation is None:
        return full_scale
    if not (0 < float(saturation) <= full_scale):
        raise ValueError(f"saturation must be in (0, {full_scale}] for {img.dtype} images, got {saturation}")
    return float(saturation)


def _check_search(search_px, shape) -> None:
    if not (isinstance(search_px, (int, np.integer)) and 4 <= search_px <= max(shape) // 2):
        raise ValueError(f"search_px must be a whole number of pixels in [4, {max(shape) // 2}], got {search_px!r}")


def locate_cross(
    img,
    saturation=None,
    prior=None,
    *,
    threshold=None,
    half_window=None,
    min_sections=MIN_SECTIONS,
    search_px=TRACK_SEARCH_PX,
    workspace=None,
) -> CrossMeasurement:
    """Locate a cross-line laser's cross in one camera image to sub-pixel precision (method.md §2).

    Parameters
    ----------
    img : ndarray, 2-D, uint8 or uint16
        The frame, ``img[row, col]``; pixel (row r, col c) is centred at image point (x=c, y=r).
    saturation : float, optional
        The sensor's saturation level; default 255 for uint8 and 65535 for uint16 (give 1023 or
        4095 for 10- or 12-bit data in 16-bit words).
    prior : CrossMeasurement, optional
        The previous frame's result. Its two lines replace the coarse detection: each stripe is
        searched only within ±``search_px`` of its prior line (the tracking path, several times
        cheaper than the full search). If the prior is lost (see ``instrument.vision._track`` and
        docs/vision.md for the rules) the full search runs instead and the result's ``search`` is
        ``"fallback"`` with ``lost_reason`` set.
    threshold : None, float or "otsu", optional
        Binarisation level used to find the stripes: None = a set level of 15 % of the contrast
        above background (at least 6 noise σ), a number = that grey level, "otsu" = Otsu's method.
        Used by the full search only.
    half_window : int, optional
        IGCF half-window h (window 2h+1 px); default from the stripe width, h = 2…4.
    min_sections : int, optional
        Fewest usable cross-sections per stripe (default 30).
    search_px : int, optional
        Half-width of the band searched around each prior line, px (default 24): the largest
        stripe motion between two frames that tracking follows.
    workspace : VisionWorkspace, optional
        Scratch memory reused from call to call (a stream keeps one; see ``VisionWorkspace``);
        None = fresh memory for this call. The result never refers to it.

    Returns
    -------
    CrossMeasurement
        Centre (x, y) px, angle θ = (φh+φv)/2 rad (positive from +x toward +y), both stripe lines
        with quality figures, perpendicularity φv − φh rad, peak level, and how it was found
        (``search``: "full", "tracked" or "fallback").

    Raises
    ------
    TypeError
        ``img`` is not a uint8/uint16 numpy array, or ``prior`` is not a CrossMeasurement.
    ValueError
        ``img`` is not 2-D or too small, ``saturation`` or ``search_px`` is out of range.
    CrossNotFound
        No cross, only one stripe, more than one cross, or a stripe too short to fit; the message
        says which.
    """
    result = locate_crosses({"frame": img}, saturation, None if prior is None else {"frame": prior},
                            threshold=threshold, half_window=half_window, min_sections=min_sections,
                            search_px=search_px, workspace=workspace)["frame"]
    if isinstance(result, CrossNotFound):
        raise result
    return result


def locate_crosses(
    images,
    saturation=None,
    priors=None,
    *,
    threshold=None,
    half_window=None,
    min_sections=MIN_SECTIONS,
    search_px=TRACK_SEARCH_PX,
    workspace=None,
) -> dict[str, CrossMeasurement | CrossNotFound]:
    """:func:`locate_cross` on several frames at once — the three cameras of one trigger.

    The same result per frame as ``locate_cross`` would give (the same rules, priors, fallback),
    faster: the fine stage runs once for all the frames' stripes, so its fixed cost is paid once.

    Parameters
    ----------
    images : mapping name → 2-D uint8/uint16 array
    saturation : float or mapping name → float, optional
        As for ``locate_cross``; one level for all frames, or one per name.
    priors : mapping name → CrossMeasurement or None, optional
        Each frame's prior (the previous result for that camera); a missing name or None: full search.
    threshold, half_window, min_sections, search_px, workspace
        As for ``locate_cross``.

    Returns
    -------
    dict name → CrossMeasurement or CrossNotFound
        A frame without a usable cross gets its ``CrossNotFound`` (returned, not raised, so one
        bad frame does not cost the others their result).

    Raises
    ------
    TypeError, ValueError
        A malformed image, saturation, prior or ``search_px`` (as ``locate_cross``).
    """
    names = list(images)
    levels = saturation if isinstance(saturation, Mapping) else dict.fromkeys(names, saturation)
    priors = priors or {}
    results: dict[str, CrossMeasurement | CrossNotFound] = {}
    jobs: dict[str, CrossJob] = {}
    lost: dict[str, str | None] = {}
    for name in names:
        img = images[name]
        level = _check_image(img, levels.get(name))
        flat = np.ascontiguousarray(img).ravel()
        prior = priors.get(name)
        if prior is not None:  # the fine stage starts from the prior's lines and checks them (``_track``)
            _check_search(search_px, img.shape)
            horizontal, vertical = prior_lines(prior)
            jobs[name] = CrossJob(flat, img.shape, horizontal, vertical, math.nan, level, "tracked", int(search_px))
            continue
        job = _full_search_job(img, flat, level, threshold, "full")
        if isinstance(job, CrossNotFound):
            results[name] = job
        else:
            jobs[name] = job
    measured = dict(zip(jobs, measure_crosses(list(jobs.values()), half_window, min_sections, workspace)))
    for name, result in measured.items():
        if jobs[name].search == "tracked":
            reason = result.reason if isinstance(result, PriorLost) else lost_after_fit(result, priors[name])
            if reason is not None:  # the prior is lost: search this frame again
                lost[name] = reason
                result = _full_search(images[name], jobs[name], threshold, half_window, min_sections, workspace)
        if isinstance(result, CrossMeasurement) and lost.get(name) is not None:
            result = replace(result, lost_reason=lost[name])
        assert not isinstance(result, PriorLost)  # a lost prior was replaced by the full search above
        results[name] = result
    return {name: results[name] for name in names}


def _full_search_job(img, flat, level, threshold, search) -> CrossJob | CrossNotFound:
    try:
        detection = find_stripes(img, level, threshold)
    except CrossNotFound as exc:
        return exc
    return CrossJob(flat, img.shape, detection.horizontal, detection.vertical, detection.background, level, search)


def _full_search(img, tracked: CrossJob, threshold, half_window, min_sections,
                 workspace) -> CrossMeasurement | CrossNotFound:
    job = _full_search_job(img, tracked.flat, tracked.saturation, threshold, "fallback")
    if isinstance(job, CrossNotFound):
        return job
    (result,) = measure_crosses([job], half_window, min_sections, workspace)
    assert not isinstance(result, PriorLost)  # a full search has no prior to lose
    return result
