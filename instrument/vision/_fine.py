"""The fine stage for several frames at once: coarse lines (or priors) → sub-pixel crosses.

Order of work (all frames' stripes together at each step, ``_bands`` and ``_igcf``): bands around
the lines → brightest run of every section → for tracked frames, the check that each band holds
its stripe (``_track``; a stripe found elsewhere gets its band laid again, once) → IGCF → one
bisquare line per stripe → intersection and angles.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from instrument.vision._bands import (
    MIN_AMPLITUDE_SIGMAS,
    StripeFit,
    cross,
    extract_bands,
    half_windows,
    plan_band,
    too_short,
    usable_centres,
)
from instrument.vision._detect import CoarseLine
from instrument.vision._igcf import brightest_runs, igcf_band
from instrument.vision._linefit import bisquare_line
from instrument.vision._track import prior_band_verdicts, reacquire_stripe
from instrument.vision._types import CrossMeasurement, CrossNotFound
from instrument.vision._workspace import VisionWorkspace


class PriorLost(NamedTuple):
    """A tracked frame whose prior no longer shows where its stripes are: the full search must run."""

    reason: str


def measure_crosses(jobs, half_window, min_sections,
                    workspace=None) -> list[CrossMeasurement | CrossNotFound | PriorLost]:
    """The sub-pixel crosses of several frames at once (every step runs once for all their stripes).

    Each entry of the result is the frame's ``CrossMeasurement``, the ``CrossNotFound`` it raised
    (returned, not raised, so that one bad frame does not cost the others their result), or for a
    tracked job (``search == "tracked"``: its lines are the prior's) a ``PriorLost``.
    ``workspace`` holds the large temporaries (a fresh one if None).
    """
    ws = VisionWorkspace() if workspace is None else workspace
    results: dict[int, CrossMeasurement | CrossNotFound | PriorLost] = {}
    lines = {number: (job.horizontal, job.vertical) for number, job in enumerate(jobs)}
    check_priors = any(job.search == "tracked" for job in jobs)
    while True:
        planned = []  # (job number, job, (horizontal plan, vertical plan))
        for number, job in enumerate(jobs):
            if number in results:
                continue
            horizontal, vertical = lines[number]
            try:
                plans = (plan_band(job.shape, horizontal, vertical, min_sections),
                         plan_band(job.shape, vertical, horizontal, min_sections))
            except CrossNotFound as exc:
                results[number] = PriorLost(f"tracked fit failed: {exc}") if job.search == "tracked" else exc
                continue
            planned.append((number, job, plans))
        if not planned:
            return [results[number] for number in range(len(jobs))]
        stripes = [(job.flat, job.shape, plan) for _, job, plans in planned for plan in plans]
        bands = extract_bands(stripes, ws, np.array([job.fallback_bg for _, job, _ in planned for _ in range(2)]))
        runs = brightest_runs(bands.values, bands.valid, ws)
        if not check_priors:
            break
        check_priors = False  # bands laid again after the check are measured as they are
        if not _follow_priors(planned, bands, runs, lines, results):
            break
    return _finish(planned, bands, runs, results, half_window, min_sections, ws, len(jobs))


def _follow_priors(planned, bands, runs, lines, results) -> bool:
    """Check each tracked frame's bands; update ``lines`` (or ``results`` with ``PriorLost``) where a
    band must be laid again. Returns whether any was."""
    tracked = [(k, number, job) for k, (number, job, _) in enumerate(planned) if job.search == "tracked"]
    if not tracked:
        return False
    verdicts = prior_band_verdicts(bands, runs, [p for _, _, plans in planned for p in plans],
                                   [line for number, _, _ in planned for line in lines[number]])
    again = False
    for k, number, job in tracked:
        new: list[CoarseLine] = list(lines[number])
        for i in range(2):
            verdict = verdicts[2 * k + i]
            if verdict is True:
                continue
            if verdict is False:  # not cleanly in the band: search ±search_px around the prior line
                verdict = reacquire_stripe(job.flat, job.shape, new[i], new[1 - i], job.search_px)
                if isinstance(verdict, str):
                    results[number] = PriorLost(verdict)
                    break
            new[i] = verdict
        again |= new != list(lines[number]) or number in results
        lines[number] = (new[0], new[1])
    return again


def _finish(planned, bands, runs, results, half_window, min_sections, ws, n_jobs):
    """IGCF, line fits and crosses of the planned frames' bands."""
    sizes = bands.starts[1:] - bands.starts[:-1]
    levels = np.array([job.saturation for _, job, _ in planned for _ in range(2)], float)
    if half_window is None:  # each stripe's window from its own width
        half_window = half_windows(bands, levels, ws).repeat(sizes)
    centres = igcf_band(
        bands.values,
        bands.valid,
        bands.background,
        levels[0] if np.logical_and.reduce(levels == levels[0]) else levels.repeat(sizes),
        half_window,
        (MIN_AMPLITUDE_SIGMAS * bands.noise).repeat(sizes),
        ws,
        runs,
        bands.by_section,
    )
    usable = usable_centres([plan for _, _, plans in planned for plan in plans], centres, bands)
    for k, (number, job, plans) in enumerate(planned):
        pair = usable[2 * k : 2 * k + 2]
        failed = next(filter(None, (too_short(plan, len(u[0]), min_sections) for plan, u in zip(plans, pair))), None)
        if failed is not None:
            results[number] = failed
            continue
        # one IRLS per stripe: a stripe's few thousand points stay in the L1 cache, which a batch of
        # all stripes does not (measured: batching the six fits of a trigger doubled their cost)
        h_fit, v_fit = (StripeFit(bisquare_line(along, centre), along, saturated, peak)
                        for along, centre, saturated, peak in pair)
        results[number] = cross(h_fit, v_fit, job.search)
    return [results[number] for number in range(n_jobs)]
