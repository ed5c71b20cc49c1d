"""Display formatting shared by the report's sections: SI values to µm and arc-seconds (degrees
beside), value ± U cells, key–value tables, and JSON without float noise for the appendix."""

from __future__ import annotations

import json
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from html import escape
from typing import Any, TypeGuard

from instrument import ARCSEC

MICRON = 1e-6
DISPLAY_DIGITS = 9  # significant digits in the appendix's JSON: 0.30000000000000004 → 0.3, nm in m


def is_number(value: Any) -> TypeGuard[float]:
    """A finite int or float (``bool`` is not a number here)."""
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)


def fmt(value: Any, scale: float, digits: int = 2) -> str:
    """``value × scale`` with ``digits`` decimals, or a dash for a missing or non-finite value."""
    if not is_number(value):
        return "—"
    return f"{value * scale:.{digits}f}"


@dataclass(frozen=True)
class Unit:
    """How one quantity is shown: ``symbol`` after values that are ``scale`` × the SI value."""

    symbol: str
    scale: float
    digits: int
    angular: bool


MICROMETRES = Unit("µm", 1 / MICRON, 2, False)
ARCSECONDS = Unit("″", 1 / ARCSEC, 2, True)


def figure_unit(key: str) -> Unit:
    """µm for a length figure (``rp_l``, ``ap_p``, ``ap_x`` …), ″ for an angle (``rp_a``, ``ap_c`` …)."""
    return ARCSECONDS if key.rsplit("_", 1)[-1] in ("a", "b", "c") else MICROMETRES


def component_unit(component: str) -> Unit:
    """µm for x, y, z; ″ for a, b, c (errors and residuals of a calibration)."""
    return MICROMETRES if component in ("x", "y", "z") else ARCSECONDS


def degrees(value: Any) -> str:
    """An angle (rad) in degrees with enough digits for arc-second figures, e.g. ``0.003644°``."""
    return f"{math.degrees(value):.6f}°" if is_number(value) else "—"


@dataclass(frozen=True)
class Figure:
    """One reported figure as the report shows it (SI values; ``None`` where the run has none)."""

    value: float | None
    expanded_uncertainty: float | None = None
    coverage_factor: float | None = None
    interval: tuple[float, float] | None = None  # the sampling confidence interval
    true: float | None = None
    meets_rule: bool | None = None  # the 25 % rule: U ≤ 0.25 × the characteristic
    ratio: float | None = None

    @classmethod
    def from_object(cls, obj: Mapping[str, Any], fallback_interval: Any = None) -> Figure:
        """From an uncertainty object (``value``, ``expanded_uncertainty``, ``coverage_factor``,
        ``confidence_interval``, ``true``, ``budget.meets_25_percent_rule`` …) of the results."""
        budget = obj.get("budget")
        if not isinstance(budget, Mapping):
            budget = {}
        rule = obj.get("meets_25_percent_rule", budget.get("meets_25_percent_rule"))
        ratio = obj.get("ratio_to_characteristic", budget.get("ratio_to_characteristic"))
        return cls(value=_number(obj.get("value")), expanded_uncertainty=_number(obj.get("expanded_uncertainty")),
                   coverage_factor=_number(obj.get("coverage_factor")),
                   interval=interval(obj.get("confidence_interval")) or interval(fallback_interval),
                   true=_number(obj.get("true")), meets_rule=rule if isinstance(rule, bool) else None,
                   ratio=_number(ratio))


def _number(value: Any) -> float | None:
    return float(value) if is_number(value) else None


def interval(value: Any) -> tuple[float, float] | None:
    """A ``[low, high]`` pair of finite numbers, or None."""
    if isinstance(value, Mapping):
        value = (value.get("low", value.get("lo")), value.get("high", value.get("hi")))
    if isinstance(value, (list, tuple)) and len(value) == 2 and all(is_number(v) for v in value):
        return float(value[0]), float(value[1])
    return None


def figure_cell(fig: Figure, unit: Unit, *, css: str = "", show_true: bool = False) -> str:
    """``<td>`` with value ± U (k), the sampling interval below, degrees beside an angle; a figure
    failing the 25 % rule is marked (class ``flag`` and a dagger); ``show_true``: the simulated
    truth on a line of its own."""
    if fig.value is None:
        return f"<td class='{css}'>—</td>" if css else "<td>—</td>"
    classes = [css] if css else []
    digits = unit.digits
    if fig.expanded_uncertainty is not None and fig.expanded_uncertainty > 0:
        # U with two significant digits (GUM 7.2.6), the value to the same decimal place
        shown = fig.expanded_uncertainty * unit.scale
        digits = min(max(unit.digits, 1 - math.floor(math.log10(shown))), unit.digits + 3)
    text = f"<span class=v>{fmt(fig.value, unit.scale, digits)}</span>"
    if fig.expanded_uncertainty is not None:
        text += f" <span class=u>± {fmt(fig.expanded_uncertainty, unit.scale, digits)}</span>"
    if fig.meets_rule is False:
        classes.append("flag")
        text += "<sup title='U above 25 % of the figure'>†</sup>"
    if unit.angular:
        text += f"<br><small class=deg>{degrees(fig.value)}</small>"
    if fig.interval is not None:
        lo, hi = fig.interval
        text += f"<br><small class=ci>[{fmt(lo, unit.scale, digits)}, {fmt(hi, unit.scale, digits)}]</small>"
    if show_true and fig.true is not None:
        text += f"<br><small class=true>true {fmt(fig.true, unit.scale, digits)}</small>"
    cls = f" class='{' '.join(classes)}'" if classes else ""
    return f"<td{cls}>{text}</td>"


def key_value_table(rows: Sequence[tuple[str, str]], *, css: str = "kv") -> str:
    """A two-column table; keys are escaped here, values are HTML already."""
    body = "".join(f"<tr><th class=l>{escape(k)}</th><td class=l>{v}</td></tr>" for k, v in rows)
    return f"<table class='{css}'>{body}</table>" if rows else ""


def first_line(text: str, limit: int = 160) -> tuple[str, bool]:
    """The first line of ``text`` (at most ``limit`` characters) and whether anything was cut."""
    stripped = text.strip()
    line = stripped.splitlines()[0] if stripped else ""
    cut = line[:limit]
    return cut, cut != stripped


def rounded(value: Any, digits: int = DISPLAY_DIGITS) -> Any:
    """``value`` with every float rounded to ``digits`` significant digits (for display only)."""
    if isinstance(value, float):
        return float(f"{value:.{digits}g}") if math.isfinite(value) else str(value)
    if isinstance(value, Mapping):
        return {str(k): rounded(v, digits) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [rounded(v, digits) for v in value]
    return value


def display_json(value: Any, *, indent: int = 1, width: int = 110) -> str:
    """JSON for a person: floats rounded (``rounded``); a list or mapping that fits in ``width``
    characters on one line."""
    def dump(v: Any, level: int) -> str:
        flat = json.dumps(v, ensure_ascii=False, default=str)
        if not isinstance(v, (Mapping, list)) or len(flat) + indent * level <= width or not v:
            return flat
        pad, inner = " " * (indent * level), " " * (indent * (level + 1))
        if isinstance(v, Mapping):
            items = [f"{inner}{json.dumps(str(k), ensure_ascii=False)}: {dump(x, level + 1)}" for k, x in v.items()]
            return "{\n" + ",\n".join(items) + "\n" + pad + "}"
        return "[\n" + ",\n".join(inner + dump(x, level + 1) for x in v) + "\n" + pad + "]"

    return dump(rounded(value), 0)
