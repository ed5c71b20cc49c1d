"""How close each component's kept model is to the noise floor of its calibration data (issue 25).

The noise floor is the pooled repeat scatter of one observation (what no curve can remove); the
kept model's held-out RMS over it, per evaluation scheme, says whether a component is there yet.
Derived from a record's evaluation rows, so records of every format version that hold an
evaluation have it.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass

from instrument.compensation._compensators import FittedModel
from instrument.compensation._evaluate import LOGO, LOPO, EvaluationTable

#: Held-out RMS of the kept model over the noise floor, per scheme, above which a component is
#: reported as not at the floor yet (``FloorRatio.at_floor``). Leaving a point out doubles the local
#: step, so a model at the floor between the points still shows 1.1–2.2 there (kept models of the
#: hard benchmark; once 3.75); a GP that smooths a 3-step ripple away shows 3–9. Leaving a group out
#: scores the curve at the calibration points only: 1.0–1.2 for a model at the floor — and about
#: the same for that GP, which is why both limits count.
FLOOR_RATIO_LIMITS = {LOPO: 3.0, LOGO: 1.25}


@dataclass(frozen=True)
class FloorRatio:
    """How close the kept model's held-out RMS is to the data's noise floor, for one component.

    Attributes
    ----------
    component : str
    method : the kept model's method
    noise_floor : pooled repeat scatter of one observation (SI): what no curve can remove
    heldout_rms : scheme → the kept model's held-out RMS (SI), for the schemes evaluated

    Notes
    -----
    A ratio of 1 is the best any model can do. Leaving one point out doubles the local step, so
    that ratio overstates the error between calibration points; leaving one group out scores the
    curve at the calibration points only. ``at_floor`` compares each with ``FLOOR_RATIO_LIMITS``.
    """

    component: str
    method: str
    noise_floor: float
    heldout_rms: dict[str, float]

    def ratio(self, scheme: str = LOPO) -> float:
        """Held-out RMS / noise floor under ``scheme`` (inf for a zero floor)."""
        rms = self.heldout_rms[scheme]
        return rms / self.noise_floor if self.noise_floor > 0 else float("inf")

    @property
    def ratios(self) -> dict[str, float]:
        return {scheme: self.ratio(scheme) for scheme in self.heldout_rms}

    @property
    def at_floor(self) -> bool:
        """No ratio above its limit (``FLOOR_RATIO_LIMITS``; schemes without a limit do not count)."""
        return all(self.ratio(s) <= FLOOR_RATIO_LIMITS[s] for s in self.heldout_rms if s in FLOOR_RATIO_LIMITS)

    def message(self) -> str:
        """One line: the ratios, and whether the component is at the floor."""
        ratios = ", ".join(f"{r:.2f} ({scheme})" for scheme, r in self.ratios.items())
        verdict = "at the noise floor" if self.at_floor else "not at the noise floor yet"
        return f"{self.component}: kept {self.method}, held-out RMS / noise floor {ratios}: {verdict}"

    def to_dict(self) -> dict:
        return {"method": self.method, "noise_floor": self.noise_floor, "heldout_rms": dict(self.heldout_rms),
                "ratio": {s: (r if math.isfinite(r) else None) for s, r in self.ratios.items()},
                "at_floor": self.at_floor}


def kept_model_floor_ratios(models: Mapping[str, FittedModel], evaluation: EvaluationTable | None
                            ) -> dict[str, FloorRatio]:
    """Component → the kept model's held-out RMS against the noise floor, from the evaluation's rows
    (components whose kept method has no row are absent)."""
    out: dict[str, FloorRatio] = {}
    if evaluation is None:
        return out
    for component, model in models.items():
        rows = evaluation.select(component, model.method)
        if rows and math.isfinite(rows[0].noise_floor):
            out[component] = FloorRatio(component, model.method, rows[0].noise_floor,
                                        {r.scheme: r.rms for r in rows if math.isfinite(r.rms)})
    return out
