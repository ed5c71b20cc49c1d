"""Reading the interferometer's environmental unit in a step, and summarising the readings of a run.

A ``FeedGap`` (no reading yet, or a stale one) or a lost feed connection is read again after the
procedure's back-off, at most ``READ_ATTEMPTS`` times; a sensor fault (``DeviceFault``) ends the
step: a run never goes on with a stale or faulty reading of the air it compensates for.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import Any

from drivers import DeviceConnectionError
from drivers.interferometer import EnvironmentReading, FeedGap
from procedures.kinds._parameters import MotionParameters, retry_wait
from procedures.kinds._protocol import StepContext

READ_ATTEMPTS = 3
QUANTITIES = ("air_temperature_k", "pressure_pa", "relative_humidity")


def read_environment(ctx: StepContext, params: MotionParameters, where: str) -> EnvironmentReading:
    """The newest reading of the station's environmental unit (see the module docstring)."""
    for attempt in range(READ_ATTEMPTS):
        try:
            return ctx.interferometer.environment()
        except (FeedGap, DeviceConnectionError) as exc:
            if attempt == READ_ATTEMPTS - 1:
                raise
            ctx.log("environment_gap", f"{where}: {exc}; reading again")
            ctx.wait(retry_wait(params, attempt))
    raise AssertionError("unreachable")


def _number(value: float) -> float | None:
    return float(value) if math.isfinite(value) else None


def environment_record(reading: EnvironmentReading) -> dict[str, Any]:
    """A reading as stored with a sample (SI; NaN, a sensor without a value, stored as null)."""
    return {"timestamp": float(reading.timestamp), "received": float(reading.received), "counter": int(reading.counter),
            "air_temperature_k": _number(reading.air_temperature_k), "pressure_pa": _number(reading.pressure_pa),
            "relative_humidity": _number(reading.relative_humidity),
            "material_temperatures_k": [_number(v) for v in reading.material_temperatures_k],
            "material_fitted": [bool(v) for v in reading.material_fitted], "faults": list(reading.faults)}


def _reading(record: Mapping[str, Any]) -> dict[str, Any]:
    return {"time": record["timestamp"], **{q: record.get(q) for q in QUANTITIES},
            "material_temperatures_k": list(record.get("material_temperatures_k") or [None, None, None])}


def _mean(values: Sequence[float | None]) -> float | None:
    known = [v for v in values if v is not None]
    return sum(known) / len(known) if known else None


def _difference(end: float | None, start: float | None) -> float | None:
    return None if end is None or start is None else end - start


def environment_summary(records: Sequence[Mapping[str, Any]]) -> dict[str, Any] | None:
    """Start, end, mean and drift (end − start) of a run's environmental readings (None: no readings)."""
    ordered = sorted(records, key=lambda r: r["timestamp"])
    if not ordered:
        return None
    start, end = _reading(ordered[0]), _reading(ordered[-1])
    materials = [r.get("material_temperatures_k") or [None] * 3 for r in ordered]
    mean = {"time": _mean([r["timestamp"] for r in ordered]),
            **{q: _mean([r.get(q) for r in ordered]) for q in QUANTITIES},
            "material_temperatures_k": [_mean([m[k] for m in materials]) for k in range(3)]}
    drift: dict[str, Any] = {q: _difference(end[q], start[q]) for q in QUANTITIES}
    drift["material_temperatures_k"] = [_difference(e, s) for e, s in zip(end["material_temperatures_k"],
                                                                          start["material_temperatures_k"])]
    return {"source": "interferometer environmental unit", "readings": len(ordered), "start": start, "end": end,
            "mean": mean, "drift": drift, "duration_s": end["time"] - start["time"]}
