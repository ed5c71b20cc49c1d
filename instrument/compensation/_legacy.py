"""Curves that only format-1 records hold, kept so those records still load and correct.

Format 1 stored the paper-era ESN alone (kind ``"esn"``: readout on [reservoir state, x̃] plus an
intercept, x̃ = measured value scaled to [−1, 1] over the training range) and a CSF-plus-ESN sum
(kind ``"sum"``). Nothing fits these any more; they are read, applied and written back unchanged.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from instrument.compensation._esn import EsnHyperparameters, Reservoir, features


@dataclass(frozen=True)
class LegacyEsnCurve:
    """Format 1's ESN curve: error = (readout(reservoir(x̃)) + intercept) · y_scale."""

    payload: dict
    hyper: EsnHyperparameters
    reservoir: Reservoir
    x_lo: float
    x_hi: float
    y_scale: float
    weights: np.ndarray
    intercept: float

    kind = "esn"

    def predict(self, x: np.ndarray) -> np.ndarray:
        x = np.asarray(x, dtype=float)
        scaled = 2.0 * (x.ravel() - self.x_lo) / (self.x_hi - self.x_lo) - 1.0
        return ((features(self.reservoir, scaled, self.hyper) @ self.weights + self.intercept) * self.y_scale
                ).reshape(x.shape)

    def to_dict(self) -> dict:
        return dict(self.payload)

    @classmethod
    def from_dict(cls, d: dict) -> LegacyEsnCurve:
        h = d["hyper"]
        hyper = EsnHyperparameters(int(h["reservoir_size"]), float(h["spectral_radius"]), float(h["leak_rate"]),
                                   float(h["input_scaling"]), float(h["ridge"]), 0.0)
        reservoir = Reservoir(np.asarray(d["w_in"], float), np.asarray(d["reservoir_rows"], int),
                              np.asarray(d["reservoir_cols"], int), np.asarray(d["reservoir_values"], float))
        return cls(dict(d), hyper, reservoir, float(d["x_lo"]), float(d["x_hi"]), float(d["y_scale"]),
                   np.asarray(d["weights"], float), float(d["intercept"]))


@dataclass(frozen=True)
class LegacySumCurve:
    """Format 1's base curve plus learned residual."""

    base: Any
    residual: Any

    kind = "sum"

    def predict(self, x: np.ndarray) -> np.ndarray:
        return np.asarray(self.base.predict(x)) + np.asarray(self.residual.predict(x))

    def to_dict(self) -> dict:
        return {"kind": self.kind, "base": self.base.to_dict(), "residual": self.residual.to_dict()}

    @classmethod
    def loader(cls, curve_from_dict: Callable[[dict], Any]) -> Callable[[dict], LegacySumCurve]:
        return lambda d: cls(curve_from_dict(d["base"]), curve_from_dict(d["residual"]))


def upgrade_v1_payload(payload: dict) -> dict:
    """A format-1 payload (id already checked) in format 2's layout.

    Models gain ``directions: []`` (format 1 recorded no approach direction) and no hysteresis;
    the evaluation keeps its rows (scheme "k-fold": every 5th interior point left out, which
    doubles the local step and overstates the error) with a note saying so.
    """
    out = dict(payload)
    out["models"] = {c: {**m, "directions": [], "hysteresis": None} for c, m in payload["models"].items()}
    evaluation = payload.get("evaluation")
    if evaluation is not None:
        out["evaluation"] = {
            "rows": evaluation["rows"],
            "data": {},
            "note": "format-1 evaluation: k-fold over every 5th interior point (leaving a point out doubles the "
                    "local step, so these figures overstate the error between calibration points)",
        }
    return out
