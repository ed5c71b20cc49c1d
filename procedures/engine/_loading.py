"""Read station and procedure files, with errors that name file, line and field."""

from __future__ import annotations

import dataclasses
import difflib
import json
from pathlib import Path
from types import UnionType
from typing import Annotated, Any, Union, get_args, get_origin

from pydantic import BaseModel, ValidationError
from pydantic_core import ErrorDetails

from procedures.kinds import KINDS, ProcedureBase
from procedures.station import ConfigError, MarkedYaml, StationFile, load_marked

PACKAGE_DIR = Path(__file__).resolve().parents[1]  # procedures/: the built-in procedures and their schemas
SCHEMA_DIR = PACKAGE_DIR / "schemas"


def _field_name(loc: tuple) -> str:
    text = ""
    for part in loc:
        if not isinstance(part, int) and not str(part).isprintable():  # a key like "\n" stays on the line
            part = repr(str(part))
        text += f"[{part}]" if isinstance(part, int) else (f".{part}" if text else str(part))
    return text or "(document)"


def _expected(error: ErrorDetails, types: list[Any]) -> str:
    """Turn one pydantic error into a sentence that says what was expected. ``types`` are the
    annotations along the error's path (see ``_walk``): ``types[-1]`` is the one at the error."""
    kind, msg = error["type"], error["msg"]
    if kind in ("extra_forbidden", "unexpected_keyword_argument"):
        parent = types[-2] if len(types) > 1 else None
        allowed = [name for name in _fields(parent) if not (name == "adapter" and _tagged(parent))]
        hint = f"; expected one of {', '.join(allowed)}" if allowed else ""
        return f"unknown field{hint}"
    tags = ", ".join(_tagged(types[-1]))
    if kind == "union_tag_invalid":  # reported at the union's ``adapter`` key, see _refine
        return f"expected one of {tags} (got {error.get('ctx', {}).get('tag')!r})"
    if kind == "union_tag_not_found":
        return f"required field is missing; expected one of {tags}"
    if kind == "model_attributes_type" and tags:
        return f"expected a mapping with 'adapter' (one of {tags}) and its settings (got {error['input']!r})"
    if kind == "missing":
        return "required field is missing"
    text = msg[0].lower() + msg[1:] if msg else kind
    if kind not in ("value_error", "assertion_error") and "input" in error:
        got = repr(error["input"])
        text += f" (got {got if len(got) <= 80 else got[:60] + f'... ({len(got)} characters)'})"
    return text.replace("value error, ", "")


# ------------------------------------------------------------------ walking the models along a loc
# A discriminated union (the device settings) puts the chosen member's tag into pydantic's loc:
# ``devices.robot.ur_rtde.hots``. The file has no such key, so the tags are taken out of the path
# (for the line and the message) and used to pick the member whose fields are listed.


def _walk(model: type[BaseModel], loc: tuple) -> tuple[tuple, list[Any]]:
    """``loc`` without union tags, and the annotation at each of its prefixes (``types[i]`` is the
    one at ``clean[:i]``; None where the models say nothing)."""
    clean: list[Any] = []
    types: list[Any] = [model]
    for part in loc:
        members = _tagged(types[-1])
        if isinstance(part, str) and part in members:
            types[-1] = members[part]
            continue
        clean.append(part)
        types.append(_element(types[-1]) if isinstance(part, int) else _fields(types[-1]).get(part))
    return tuple(clean), types


def _fields(annotation: Any) -> dict[str, Any]:
    """Field name → annotation of the model or dataclass inside ``annotation`` (``X | None`` too);
    for a union of several models, none (the tag decides, see ``_tagged``)."""
    candidates = [arg for arg in _members(annotation) if _is_class(arg)]
    if len(candidates) != 1:
        return {}
    kind = candidates[0]
    if issubclass(kind, BaseModel):
        return {name: info.annotation for name, info in kind.model_fields.items()}
    if dataclasses.is_dataclass(kind):
        return {f.name: f.type for f in dataclasses.fields(kind)}
    return {}


def _tagged(annotation: Any) -> dict[str, type[BaseModel]]:
    """The models of a union discriminated on ``adapter`` (a lone such model counts), by tag."""
    found: dict[str, type[BaseModel]] = {}
    for member in _members(annotation):
        if _is_class(member) and issubclass(member, BaseModel) and "adapter" in member.model_fields:
            for tag in get_args(member.model_fields["adapter"].annotation):
                found[tag] = member
    return found


def _members(annotation: Any) -> list[Any]:
    """The alternatives of a union, nested unions and ``Annotated`` unwrapped and ``None`` left
    out; or the annotation itself."""
    if get_origin(annotation) is Annotated:
        return _members(get_args(annotation)[0])
    if get_origin(annotation) in (Union, UnionType):
        return [member for arg in get_args(annotation) for member in _members(arg)]
    return [] if annotation is None or annotation is type(None) else [annotation]


def _is_class(annotation: Any) -> bool:
    """A plain class (``list[X]`` passes for a type on some Python versions)."""
    return isinstance(annotation, type) and get_origin(annotation) is None


def _element(annotation: Any) -> Any:
    """The element type of ``list[X]`` (or ``list[X] | None``)."""
    for member in _members(annotation):
        if get_origin(member) is list and get_args(member):
            return get_args(member)[0]
    return None


def _refine(loc: tuple, error: ErrorDetails, marked: MarkedYaml) -> tuple:
    """Point at the key the problem is about: a model-level check names its field first
    ("groups is 2 but ..."), a bad or missing adapter is reported at ``adapter``."""
    if error["type"] in ("union_tag_invalid", "union_tag_not_found"):
        return loc + ("adapter",)
    if error["type"] != "value_error":
        return loc
    words = error["msg"].replace("Value error, ", "").split()
    if words and loc + (words[0],) in marked.key_lines:
        return loc + (words[0],)
    return loc


def _problems(exc: ValidationError, marked: MarkedYaml, model: type[BaseModel], prefix: tuple = ()) -> list[str]:
    found = []
    for error in exc.errors():
        clean, types = _walk(model, prefix + tuple(error["loc"]))
        loc = _refine(clean, error, marked)
        found.append((marked.line_of(loc), f"{marked.where(loc)}: {_field_name(loc)}: {_expected(error, types)}"))
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
    from instrument.pose import Geometry
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
    if path.exists():  # a folder, FIFO or device: the reader says why it is no procedure file
        return path
    built_ins = sorted(candidate.stem for candidate in PACKAGE_DIR.glob("*.yaml"))
    close = difflib.get_close_matches(path.stem, built_ins, n=1)
    hint = f"did you mean {close[0]}? " if close else ""
    raise ConfigError([f"{name_or_path}: no such procedure file (and no built-in procedure of that name; "
                       f"{hint}built-ins: {', '.join(built_ins)})"])


def load_procedure(path: str | Path, text: str | None = None, *, stored: bool = False) -> ProcedureBase:
    """Parse and validate a procedure file: ``procedure:`` names the kind, whose model checks the rest.

    ``stored``: the text of a run already in the store (resumed): rules made for new runs after it
    was queued (e.g. at least 2 repeats) do not refuse it; the plan-size limit still holds.
    """
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
        return model.model_validate(data, context={"stored": stored})
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
