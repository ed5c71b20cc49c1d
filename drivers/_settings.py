"""What every adapter's settings model shares, and the one way a plain mapping becomes one.

Each device kind declares one pydantic model per adapter (in its own ``_settings.py``) and an
annotated union discriminated on ``adapter``. The station file is validated against those unions
(``procedures`` reports problems with file and line); ``create()`` accepts either a validated
model or a plain mapping, which goes through the same union here and fails with one clear line.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from typing import Any, Generic, TypeVar, get_args, get_origin

from pydantic import BaseModel, ConfigDict, TypeAdapter, ValidationError
from pydantic_core import ErrorDetails

from drivers._errors import SettingsError

SettingsT = TypeVar("SettingsT")


def _adapter_required(schema: dict[str, Any]) -> None:
    # The model has a default tag (handy in code), but a station file must name its adapter.
    if "adapter" in schema.get("properties", {}):
        schema["required"] = ["adapter", *[key for key in schema.get("required", []) if key != "adapter"]]


class DeviceSettings(BaseModel):
    """Base of every adapter's settings: unknown keys are errors and a model never changes.

    Numbers given for text settings become text: YAML reads ``serial: 21234567`` (a Basler serial)
    or ``axis: 1`` (a GCS axis) as integers.
    """

    model_config = ConfigDict(extra="forbid", frozen=True, coerce_numbers_to_str=True,
                              json_schema_extra=_adapter_required)




class SettingsUnion(Generic[SettingsT]):
    """One kind's annotated union of adapter models, and the validation ``create()`` uses.

    Parameters
    ----------
    annotation
        The kind's union, e.g. ``RotaryTableSettings``.
    kind : str
        The device kind, for messages (``"rotary_table"``).
    """

    def __init__(self, annotation: Any, kind: str) -> None:
        self.kind = kind
        self.models = adapter_models(annotation)
        self._adapter: TypeAdapter[SettingsT] = TypeAdapter(annotation)

    def validate(self, settings: SettingsT | Mapping[str, Any], *, name: str) -> SettingsT:
        """``settings`` as a model of one adapter: a model is returned as it is, a mapping with
        ``adapter`` is validated.

        Raises
        ------
        SettingsError
            Naming the device, the adapter and every problem, e.g. ``rotary_table 't' (gcs_serial):
            unknown setting 'unit'; expected one of port, baudrate, axis, timeout, retries, poll_interval``.
        """
        data = dict(settings) if isinstance(settings, Mapping) else settings
        try:
            return self._adapter.validate_python(data)
        except ValidationError as exc:
            adapter = data.get("adapter") if isinstance(data, dict) else None
            device = f"{self.kind} {name!r}" + (f" ({adapter})" if adapter in self.models else "")
            problems = "; ".join(describe_error(error, self.models) for error in exc.errors())
            raise SettingsError(f"{device}: {problems}") from None


def describe_error(error: ErrorDetails, tags: Mapping[str, type[BaseModel]]) -> str:
    """One pydantic error of a settings union as words (the tag left out of the path)."""
    kind, loc = error["type"], tuple(error["loc"])
    model = tags.get(str(loc[0])) if loc else None
    path = loc[1:] if model is not None else loc
    where = ".".join(str(part) for part in path)
    if kind == "union_tag_invalid":
        return f"unknown adapter {error['input'].get('adapter')!r}; expected one of {', '.join(tags)}"
    if kind == "union_tag_not_found":
        return f"no adapter given; expected one of {', '.join(tags)}"
    if kind in ("extra_forbidden", "unexpected_keyword_argument"):
        known = [f for f in allowed_keys(model, path[:-1]) if f != "adapter"] if model is not None else []
        hint = f"; expected one of {', '.join(known)}" if known else ""
        return f"unknown setting {where!r}{hint}"
    if kind == "missing":
        return f"setting {where!r} is missing"
    if kind == "model_attributes_type" and not path:
        return f"expected a mapping of settings, got {error['input']!r}"
    message = error["msg"][:1].lower() + error["msg"][1:]
    if kind not in ("value_error", "assertion_error"):
        message += f" (got {error['input']!r})"
    message = message.replace("value error, ", "")
    return f"{where}: {message}" if where else message


def adapter_models(annotation: Any) -> dict[str, type[BaseModel]]:
    """The models of a settings union by their ``adapter`` tag, in declaration order."""
    members: list[Any] = []
    _collect_models(annotation, members)
    return {member.model_fields["adapter"].default: member for member in members if "adapter" in member.model_fields}


def _collect_models(annotation: Any, found: list[Any]) -> None:
    if isinstance(annotation, type) and issubclass(annotation, BaseModel):
        found.append(annotation)
        return
    if get_origin(annotation) is not None or hasattr(annotation, "__metadata__"):
        for arg in get_args(annotation):
            _collect_models(arg, found)


def allowed_keys(model: type[BaseModel] | None, path: tuple[Any, ...]) -> list[str]:
    """The keys a mapping at ``path`` inside ``model`` may hold (nested models and dataclasses)."""
    current: Any = model
    for part in path:
        fields = _fields_of(current)
        if part not in fields:
            return []
        current = _inner_type(fields[part])
    return list(_fields_of(current))


def _fields_of(kind: Any) -> dict[str, Any]:
    if isinstance(kind, type) and issubclass(kind, BaseModel):
        return {name: info.annotation for name, info in kind.model_fields.items()}
    if isinstance(kind, type) and dataclasses.is_dataclass(kind):
        return {f.name: f.type for f in dataclasses.fields(kind)}
    return {}


def _inner_type(annotation: Any) -> Any:
    """The model or dataclass inside ``X | None`` (or the annotation itself)."""
    if _fields_of(annotation):
        return annotation
    for arg in get_args(annotation):
        inner = _inner_type(arg)
        if _fields_of(inner):
            return inner
    return annotation
