"""GigE Vision on loopback: three twin cameras through Aravis, the rates they sustain, lost packets and
resends, and trigger-to-timestamp jitter. A benchmark, not a test.

    SIM_LOOPBACK_BLOCK=127.0.60 OMP_NUM_THREADS=1 .venv/bin/python benchmarks/gige.py [--quick]

1. **Highest sustained rate**, ROI 320 × 320 and full frame (1024 × 1040) Mono8: the three twins
   driven by their trigger line (``line_pulses`` on the shared controller clock) at rising rates for
   ``--seconds`` each; a rate is sustained when every pulse gives a complete triple (no missed
   trigger, no lost frame). Twice: with ``render: static`` (one frame per setting, sent for every
   trigger: the transport alone, GVCP + GVSP + Aravis) and with ``render: pose`` (every frame rendered
   at its true pose: what the simulated cell gives).
2. **Lost packets and resends**: 1 % of the payload packets dropped by the twins at a sustained
   rate: packets dropped, resent (twin), resent (Aravis's count), frames lost.
3. **Trigger to timestamp**: with the line, the stamps' residual from a straight line through the
   pulse times (the camera clock's jitter, 1 µs σ set); with software triggers, the latency from the
   host's ``TriggerSoftware`` call to the exposure start (controller clock), median and p99.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from drivers.camera import AravisCamera, AravisSettings, CameraTriplet, Roi, aravis_available
from tests._gige import gige_twins, shared_clock


def _triplet(twins, **settings) -> CameraTriplet:
    return CameraTriplet({name: AravisCamera(AravisSettings(address=twin.endpoints["host"], **settings), name=name)
                          for name, twin in zip("xyz", twins)})


def run_stream(twins, rate: float, seconds: float, roi: Roi | None) -> dict:
    """One line-triggered stream of ``seconds`` at ``rate``: what came."""
    count = max(10, int(rate * seconds))
    before = [twin.call("stats") for twin in twins]
    with _triplet(twins, trigger_source="Line0", buffers=64) as triplet:
        stream = triplet.start_stream(rate, roi=roi, exposure_s=5e-4, hardware_trigger=True, timeout=5.0)
        with stream:
            t0 = twins[0].call("clock")["controller_now"] + 0.2
            for twin in twins:
                twin.call("line_pulses", rate_hz=rate, t0=t0, count=count)
            triples = []
            try:
                while len(triples) < count:
                    triple = stream.next_triple()
                    if triple is None:
                        break
                    triples.append(triple)
            except Exception as error:  # a rate far too high: the stream times out
                print(f"    ({type(error).__name__}: {error})")
            for twin in twins:
                twin.call("line_stop")
            stream.stop()
            stats = {name: camera.statistics() for name, camera in triplet.cameras.items()}  # type: ignore[attr-defined]
        stamps = {name: np.array([t.timestamps[name] for t in triples if name in t.timestamps]) for name in "xyz"}
        indices = {name: np.array([t.index for t in triples if name in t.timestamps]) for name in "xyz"}
    complete = sum(t.complete for t in triples)
    twin_stats = [twin.call("stats") for twin in twins]
    # Where missing frames went: the twins (busy, memory full, or frames still queued when the stream
    # ended), the receiving side (Aravis had no free buffer: underruns; incomplete frames: failures).
    where = {key: sum(a[key] - b[key] for a, b in zip(twin_stats, before)) for key in ("missed", "overflow", "sent")}
    where["queued"] = sum(a["queued"] for a in twin_stats)
    where["underruns"] = sum(s["underruns"] for s in stats.values())
    where["failures"] = sum(s["failures"] for s in stats.values())
    return {"rate": rate, "pulses": count, "triples": len(triples), "complete": complete,
            "missed": sum(stream.stats.missed.values()), "lost": sum(stream.stats.lost.values()),
            "aravis": stats, "twins": twin_stats, "where": where, "t0": t0, "stamps": stamps, "indices": indices}


def highest_rate(twins, rates, seconds, roi) -> tuple[float | None, list[dict]]:
    best, results = None, []
    for rate in rates:
        result = run_stream(twins, rate, seconds, roi)
        results.append(result)
        ok = result["complete"] == result["pulses"]
        where = result["where"]
        print(f"    {rate:7.1f} Hz: {result['complete']}/{result['pulses']} complete triples, "
              f"missed {result['missed']}, lost {result['lost']} (twins: sent {where['sent']}, busy {where['missed']}, "
              f"memory full {where['overflow']}, still queued {where['queued']}; Aravis: no buffer "
              f"{where['underruns']}, failed {where['failures']})")
        if not ok:
            break
        best = rate
    return best, results


def software_latency(twins, shots: int) -> np.ndarray:
    """s from the host's trigger call to the exposure start, on the shared controller clock."""
    twin = twins[0]
    origin = time.monotonic() - twin.call("clock")["controller_now"]
    latencies = []
    with AravisCamera(AravisSettings(address=twin.endpoints["host"], roi=Roi(360, 360, 320, 320)), name="x") as camera:
        for _ in range(shots):
            called = time.monotonic() - origin
            frame = camera.grab(5.0)
            record = next(r for r in reversed(twin.call("frames", last=20)) if r["block_id"] == frame.frame_id)
            latencies.append(record["start"] - called)
    return np.array(latencies)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="fewer rates, shorter streams")
    parser.add_argument("--seconds", type=float, default=2.0, help="s per rate (default 2)")
    args = parser.parse_args()
    why = aravis_available()
    if why is not None:
        print(f"skipped: {why}")
        return 0
    seconds = 1.0 if args.quick else args.seconds
    roi = Roi(352, 360, 320, 320)
    with tempfile.TemporaryDirectory() as directory:
        clock = shared_clock(Path(directory) / "trajectories")
        for render in ("static", "pose"):
            with gige_twins("xyz", trajectories=clock, render=render) as twins:
                print(f"render: {render}")
                # 320 rows read out in 1.54 ms (+ 50 µs): a sensor so cut takes at most ≈ 630 pulses/s.
                roi_rates = [100, 200, 400, 600] if render == "static" else [50, 100, 150, 200, 400]
                full_rates = [10, 25, 50, 100, 150] if render == "static" else [5, 10, 20, 40, 60]
                if args.quick:
                    roi_rates, full_rates = roi_rates[:3], full_rates[:3]
                print("  ROI 320 x 320 Mono8:")
                best_roi, roi_results = highest_rate(twins, roi_rates, seconds, roi)
                print("  full frame 1024 x 1040 Mono8:")
                best_full, _ = highest_rate(twins, full_rates, seconds, None)
                print(f"  highest sustained: ROI {best_roi} Hz, full frame {best_full} Hz")
                if render == "static":
                    rate = float(best_roi or roi_rates[0]) / 2
                    before = [twin.call("stats")["channel"] for twin in twins]
                    for twin in twins:
                        twin.call("drop_packets", fraction=0.01, seed=11)
                    result = run_stream(twins, rate, seconds, roi)
                    for twin in twins:
                        twin.call("clear_faults")
                    after = [twin.call("stats")["channel"] for twin in twins]
                    dropped = sum(a["dropped"] - b["dropped"] for a, b in zip(after, before))
                    resent = sum(a["resent"] - b["resent"] for a, b in zip(after, before))
                    aravis_resent = sum(s["resent_packets"] for s in result["aravis"].values())
                    aravis_missing = sum(s["missing_packets"] for s in result["aravis"].values())
                    print(f"  1 % drop at {rate:g} Hz (ROI): {result['complete']}/{result['pulses']} complete, "
                          f"{dropped} packets dropped, {resent} resent by the twins, Aravis counted {aravis_resent} "
                          f"resent and {aravis_missing} missing, {result['lost']} frames lost")
                    good = next(r for r in reversed(roi_results) if r["complete"] == r["pulses"])
                    residuals = []
                    for name in "xyz":
                        pulses = good["t0"] + good["indices"][name] / good["rate"]
                        stamps = good["stamps"][name] - 0.25e-3  # image mean time → exposure start
                        fit = np.polyfit(pulses, stamps, 1)
                        residuals.append(stamps - np.polyval(fit, pulses))
                    residual = np.concatenate(residuals)
                    print(f"  line trigger → stamp at {good['rate']:g} Hz: residual σ {np.std(residual) * 1e6:.2f} µs, "
                          f"max {np.max(np.abs(residual)) * 1e6:.2f} µs (the clocks' 1 µs jitter)")
                    latency = software_latency(twins, 20 if args.quick else 100)
                    print(f"  software trigger → exposure start: median {np.median(latency) * 1e3:.3f} ms, "
                          f"p99 {np.percentile(latency, 99) * 1e3:.3f} ms, σ {np.std(latency) * 1e3:.3f} ms")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
