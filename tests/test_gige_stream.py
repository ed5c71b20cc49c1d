"""Live streaming from three GigE twins through Aravis: ``CameraTriplet.start_stream`` with a hardware line.

The twins' trigger line (``line_pulses``, the cell's trigger generator) runs on the shared controller
clock; each camera stamps its frames on its own clock. Checked against the twins' truth: the frames
come while the pulses still run (live, not after ``stop()``), one complete triple per pulse with
consecutive frame ids, each camera's stamps follow its true clock (drift within the stamp jitter's
reach), a late trigger shows in the stamps by its delay, and an overtriggered camera misses pulses,
counted, never filled.
"""

from __future__ import annotations

import numpy as np
import pytest

from drivers.camera import AravisCamera, AravisSettings, CameraTriplet, Roi, aravis_available
from tests._gige import gige_twins, shared_clock

WHY_NOT = aravis_available()
pytestmark = [pytest.mark.timeout(120),
              pytest.mark.skipif(WHY_NOT is not None, reason=f"Aravis cannot be used here: {WHY_NOT}")]
RATE = 50.0
PULSES = 40
ROI = Roi(360, 360, 320, 320)


@pytest.fixture(scope="module")
def twins(tmp_path_factory):
    clock = shared_clock(tmp_path_factory.mktemp("gige-clock"))
    with gige_twins("xyz", trajectories=clock) as started:
        yield started


def _triplet(twins) -> CameraTriplet:
    return CameraTriplet({name: AravisCamera(AravisSettings(address=twin.endpoints["host"], trigger_source="Line0"),
                                             name=name) for name, twin in zip("xyz", twins)})


def test_a_line_triggered_stream_is_live_complete_and_on_each_cameras_clock(twins):
    with _triplet(twins) as triplet:
        stream = triplet.start_stream(RATE, roi=ROI, exposure_s=1e-3, hardware_trigger=True, timeout=10.0)
        with stream:
            t0 = twins[0].call("clock")["controller_now"] + 0.2
            for twin in twins:
                twin.call("line_pulses", rate_hz=RATE, t0=t0, count=PULSES, line="Line0")
            first = stream.next_triple()
            assert first is not None and first.complete
            # Live: the first triple is here before stop() (the emulator's replay gives nothing until
            # then), and while pulses are still to come.
            assert twins[0].call("clock")["controller_now"] < t0 + (PULSES - 1) / RATE
            triples = [first] + [stream.next_triple() for _ in range(PULSES - 1)]
            for twin in twins:
                assert twin.call("line_stop")["fired"] == PULSES
            # Aravis's counters and the stray buffers, to tell why, should a triple ever be incomplete
            # (it was, once, on a loaded CI host; not reproduced since).
            counters = {name: {**camera.statistics(), "stray_buffers": camera.stray_buffers}
                        for name, camera in triplet.cameras.items()}
            stream.stop()
        incomplete = [(t.index, sorted(t.frame_ids)) for t in triples if not t.complete]
        assert [t.index for t in triples] == list(range(PULSES)) and not incomplete, (incomplete, counters)
        for name, twin in zip("xyz", twins):
            ids = np.array([t.frame_ids[name] for t in triples])
            assert np.all(np.diff(ids) == 1)
            stamps = np.array([t.timestamps[name] for t in triples])  # image mean time, camera clock, s
            pulses = t0 + np.arange(PULSES) / RATE
            rate, offset = np.polyfit(pulses, stamps - 0.5e-3, 1)
            truth = twin.call("clock")
            assert abs(rate - (1.0 + truth["drift"])) < 5e-6  # 1 µs stamp jitter over 0.8 s: ≈ 1e-6
            assert abs(offset - truth["offset"]) < 1e-4
            assert np.std(stamps - 0.5e-3 - (offset + rate * pulses)) < 5e-6
            assert stream.stats.frames[name] == PULSES and stream.stats.missed[name] == 0


def test_a_late_trigger_is_seen_in_the_stamps_and_overtriggering_is_counted_never_filled(twins):
    x = twins[0]
    settings = AravisSettings(address=x.endpoints["host"], trigger_source="Line0")
    with CameraTriplet({"x": AravisCamera(settings, name="x")}) as triplet:
        # Full frame at 250 Hz: 1040 rows take 5.0 ms to read out, so every other pulse is missed.
        stream = triplet.start_stream(250.0, exposure_s=1e-3, hardware_trigger=True, timeout=10.0)
        with stream:
            t0 = x.call("clock")["controller_now"] + 0.2
            x.call("late_trigger", delay=1.5e-3, count=1)
            x.call("line_pulses", rate_hz=250.0, t0=t0, count=20, line="Line0")
            triples = [stream.next_triple() for _ in range(19)]
            x.call("line_stop")
            stream.stop()
        captured = [t for t in triples if t is not None and t.complete]
        missed = [t for t in triples if t is not None and not t.complete]
        assert len(captured) >= 8 and len(missed) >= 8 and stream.stats.missed["x"] == len(missed)
        assert all("trigger missed" in t.missing["x"] for t in missed)
        ids = [t.frame_ids["x"] for t in captured]
        assert ids == list(range(ids[0], ids[0] + len(ids)))  # nothing filled in: the ids stay consecutive
        stamps = np.array([t.timestamps["x"] for t in captured])
        # The first exposure started 1.5 ms late: the next one follows it 1.5 ms less than two periods on.
        steps = np.diff(stamps)
        assert abs(steps[0] - (2 / 250.0 - 1.5e-3)) < 2e-5 and np.all(np.abs(steps[1:] - 2 / 250.0) < 2e-5)
