"""Read station and procedure files, with errors that name file, line and field."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from pydantic import BaseModel, ValidationError

from instrument.pose import Geometry
from procedures._errors import ConfigError
from procedures._models import StationFile
from procedures._yamlmarks import MarkedYaml, load_marked
from procedures.kinds import KINDS, ProcedureBase

PACKAGE_DIR = Path(__file__).resolve().parent
SCHEMA_DIR = PACKAGE_DIR / "schemas"


def _field_name(loc: tuple) -> str:
    text = ""
    for part in loc:
        text += f"[{part}]" if isinstance(part, int) else (f".{part}" if text else str(part))
    return text or "(document)"


def _expected(error: dict, model: type[BaseModel], loc: tuple) -> str:
    """Turn one pydantic error into a sentence that says what was expected."""
    kind, msg = error["type"], error["msg"]
    if kind == "extra_forbidden":
        allowed = _allowed_fields(model, loc[:-1])
        hint = f"; expected one of: {', '.join(allowed)}" if allowed else ""
        return f"unknown field{hint}"
    if kind == "missing":
        return "required field is missing"
    text = msg[0].lower() + msg[1:] if msg else kind
    if kind not in ("value_error", "assertion_error") and "input" in error:
        text += f" (got {error['input']!r})"
    return text.replace("value error, ", "")


def _allowed_fields(model: type[BaseModel], loc: tuple) -> list[str]:
    current: Any = model
    for part in loc:
        if isinstance(part, int) or not (isinstance(current, type) and issubclass(current, BaseModel)):
            current = _inner_model(current)
            if isinstance(part, int):
                continue
        if not (isinstance(current, type) and issubclass(current, BaseModel)) or part not in current.model_fields:
            return []
        current = current.model_fields[part].annotation
    current = _inner_model(current)
    if isinstance(current, type) and issubclass(current, BaseModel):
        return list(current.model_fields)
    return []


def _inner_model(annotation: Any) -> Any:
    """The BaseModel inside ``X | None`` or ``list[X]``, if any."""
    if isinstance(annotation, type) and issubclass(annotation, BaseModel):
        return annotation
    for arg in getattr(annotation, "__args__", ()) or ():
        found = _inner_model(arg)
        if found is not None:
            return found
    return None


def _refine(loc: tuple, error: dict, marked: MarkedYaml) -> tuple:
    """A model-level check names its field first ("groups is 2 but ..."): point at that field."""
    if error["type"] != "value_error":
        return loc
    words = error["msg"].replace("Value error, ", "").split()
    if words and loc + (words[0],) in marked.key_lines:
        return loc + (words[0],)
    return loc


def _problems(exc: ValidationError, marked: MarkedYaml, model: type[BaseModel], prefix: tuple = ()) -> list[str]:
    found = []
    for error in exc.errors():
        loc = _refine(prefix + tuple(error["loc"]), error, marked)
        found.append((marked.line_of(loc), f"{marked.where(loc)}: {_field_name(loc)}: "
                                            f"{_expected(error, model, tuple(error['loc']))}"))
    return [text for _, text in sorted(found, key=lambda item: item[0])]


def load_station(path: str | Path, *, check_geometry: bool = True) -> StationFile:
    """Parse and validate a station file.

    Raises
    ------
    ConfigError
        Listing every problem as ``file:line: field: what was expected``.
    """
    marked = load_marked(path)
    if not isinstance(marked.data, dict):
        raise ConfigError(
            [f"{marked.source}:1: (document): expected a mapping with name, devices, geometry, frames, envelope"]
        )
    try:
        station = StationFile.model_validate(marked.data)
    except ValidationError as exc:
        raise ConfigError(_problems(exc, marked, StationFile)) from None
    if check_geometry:
        problem = _check_geometry(station.geometry)
        if problem:
            raise ConfigError([f"{marked.where(('geometry',))}: geometry: {problem}"])
    return station


def _check_geometry(geometry: dict) -> str | None:
    """Let ``instrument.pose.Geometry.from_dict`` judge the geometry."""
    try:
        Geometry.from_dict(geometry)
    except (TypeError, ValueError, KeyError) as exc:
        return f"not a valid geometry: {exc}"
    return None


def resolve_procedure_path(name_or_path: str | Path) -> Path:
    """A file path, or the name of a procedure shipped in ``procedures/`` (with or without .yaml)."""
    path = Path(name_or_path)
    if path.is_file():
        return path
    for candidate in (PACKAGE_DIR / f"{name_or_path}.yaml", PACKAGE_DIR / str(name_or_path)):
        if candidate.is_file():
            return candidate
    raise ConfigError([f"{name_or_path}: no such procedure file (and no built-in procedure of that name; "
                       f"built-ins: {', '.join(sorted(KINDS))})"])


def load_procedure(path: str | Path, text: str | None = None) -> ProcedureBase:
    """Parse and validate a procedure file: ``procedure:`` names the kind, whose model checks the rest."""
    marked = load_marked(path, text)
    data = marked.data
    if not isinstance(data, dict):
        raise ConfigError([f"{marked.source}:1: (document): expected a mapping with 'procedure' and 'parameters'"])
    name = data.get("procedure")
    kind = KINDS.get(name) if isinstance(name, str) else None
    if kind is None:
        got = "missing" if name is None else f"got {name!r}"
        raise ConfigError([f"{marked.where(('procedure',))}: procedure: expected one of "
                           f"{', '.join(KINDS)} ({got})"])
    model = kind.file_model
    try:
        return model.model_validate(data)
    except ValidationError as exc:
        raise ConfigError(_problems(exc, marked, model)) from None


def detect_kind(path: str | Path) -> str:
    """'station' or 'procedure', judged from the top-level keys."""
    marked = load_marked(path)
    if isinstance(marked.data, dict) and "procedure" in marked.data:
        return "procedure"
    if isinstance(marked.data, dict) and "devices" in marked.data:
        return "station"
    raise ConfigError([f"{marked.source}:1: (document): neither a procedure file (no 'procedure:') "
                       "nor a station file (no 'devices:')"])


def json_schemas() -> dict[str, dict]:
    """Editor schemas (JSON Schema draft 2020-12), one per file kind, from the models."""
    schemas = {"station": StationFile.model_json_schema()}
    for name, kind in KINDS.items():
        schemas[name] = kind.file_model.model_json_schema()
    for name, schema in schemas.items():
        schema["$schema"] = "https://json-schema.org/draft/2020-12/schema"
        schema["$id"] = f"https://opr-instrument.invalid/schemas/{name}.json"
    return schemas


def write_schemas(directory: Path = SCHEMA_DIR) -> list[Path]:
    directory.mkdir(parents=True, exist_ok=True)
    written = []
    for name, schema in json_schemas().items():
        path = directory / f"{name}.json"
        path.write_text(json.dumps(schema, indent=2, sort_keys=True) + "\n", encoding="utf-8")
        written.append(path)
    return written


if __name__ == "__main__":  # python -m procedures._loading  → regenerate the committed schemas
    for written_path in write_schemas():
        print(written_path)
