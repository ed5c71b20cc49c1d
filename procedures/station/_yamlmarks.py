"""Load YAML while remembering the line of every field, so errors can name ``file:line``.

Input is not trusted: the file is read as a bounded, regular UTF-8 file (``procedures.station._files``),
and the parsed node graph is checked before anything is built from it: no recursive alias, at
most ``MAX_NODES`` nodes once aliases are expanded (a "billion laughs" file is refused, not
expanded), at most ``MAX_DEPTH`` levels of nesting.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import yaml

from procedures.station._errors import ConfigError
from procedures.station._files import InputRefused, read_text_file

Path_ = tuple[Any, ...]
MAX_NODES = 100_000
MAX_DEPTH = 32


class MarkedYaml:
    """A parsed YAML document plus the 1-based line of each field path.

    ``lines[("parameters", "cycles")]`` is the line of the *value* of that field; ``key_lines``
    the line of its key. The empty path is the document itself.
    """

    def __init__(self, data: Any, lines: dict[Path_, int], key_lines: dict[Path_, int], source: str) -> None:
        self.data = data
        self.lines = lines
        self.key_lines = key_lines
        self.source = source

    def line_of(self, path: Path_) -> int:
        """The line of ``path`` or of its nearest existing ancestor (a missing field is reported
        at the mapping that should hold it)."""
        path = tuple(path)
        while path:
            if path in self.key_lines:
                return self.key_lines[path]
            if path in self.lines:
                return self.lines[path]
            path = path[:-1]
        return self.lines.get((), 1)

    def where(self, path: Path_) -> str:
        return f"{self.source}:{self.line_of(path)}"


def load_marked(path: str | Path, text: str | None = None) -> MarkedYaml:
    """Parse ``path`` (or ``text``, named ``path``) into a ``MarkedYaml``.

    Raises
    ------
    ConfigError
        When the file cannot be read or is not valid YAML (with the parser's line).
    """
    source = str(path)
    if text is None:
        try:
            text = read_text_file(path, what="YAML file")
        except InputRefused as exc:
            raise ConfigError([str(exc)]) from None
    try:
        node = yaml.compose(text, Loader=yaml.SafeLoader)
        if node is not None:
            _check_size(node, source)
        data = _construct(node)
    except ConfigError:
        raise
    except RecursionError:
        raise ConfigError([f"{source}:1: YAML: nested too deeply (at most {MAX_DEPTH} levels)"]) from None
    except ValueError as exc:  # a scalar the constructor cannot convert (an integer of 5000 digits ...)
        what = "an integer with too many digits" if "digits" in str(exc) else _first_line(exc)
        raise ConfigError([f"{source}:1: YAML: {what}"]) from None
    except yaml.MarkedYAMLError as exc:
        mark = exc.problem_mark or exc.context_mark
        line = mark.line + 1 if mark else 1
        raise ConfigError([f"{source}:{line}: YAML syntax: {exc.problem or _first_line(exc)}"]) from None
    except yaml.reader.ReaderError as exc:  # a character YAML does not allow; it has a position, not a mark
        line = text.count("\n", 0, exc.position) + 1
        what = f"#x{exc.character:04x}" if isinstance(exc.character, int) else repr(exc.character)
        raise ConfigError([f"{source}:{line}: YAML: unacceptable character {what}: {exc.reason}"]) from None
    except yaml.YAMLError as exc:
        raise ConfigError([f"{source}:1: YAML: {_first_line(exc)}"]) from None
    lines: dict[Path_, int] = {}
    key_lines: dict[Path_, int] = {}
    if node is not None:
        _walk(node, (), lines, key_lines)
    return MarkedYaml(data, lines, key_lines, source)


def _construct(node: yaml.Node | None) -> Any:
    """The Python value of a checked node graph (what ``yaml.safe_load`` would give)."""
    if node is None:
        return None
    loader = yaml.SafeLoader("")
    try:
        return loader.construct_document(node)
    finally:
        loader.dispose()


def _check_size(root: yaml.Node, source: str) -> None:
    """Refuse a recursive alias, more than ``MAX_NODES`` nodes once aliases are expanded, or more
    than ``MAX_DEPTH`` levels. Iterative, and each distinct node is visited once (aliases share
    nodes), so the check costs what the file costs, not what it would expand to."""
    size: dict[int, int] = {}
    depth: dict[int, int] = {}
    on_path: set[int] = set()
    stack: list[tuple[yaml.Node, bool]] = [(root, False)]
    while stack:
        node, children_done = stack.pop()
        key = id(node)
        children = _children(node)
        if children_done:
            on_path.discard(key)
            size[key] = 1 + sum(size[id(child)] for child in children)
            depth[key] = 1 + max((depth[id(child)] for child in children), default=0)
            if size[key] > MAX_NODES:
                raise ConfigError([f"{source}:{node.start_mark.line + 1}: YAML: more than {MAX_NODES} values once "
                                   "aliases are expanded (an alias bomb?)"])
            if depth[key] > MAX_DEPTH:
                raise ConfigError([f"{source}:{node.start_mark.line + 1}: YAML: nested more than {MAX_DEPTH} "
                                   "levels deep"])
            continue
        if key in size:
            continue
        if key in on_path:
            raise ConfigError([f"{source}:{node.start_mark.line + 1}: YAML: an alias refers to a value that "
                               "contains it (recursive alias)"])
        on_path.add(key)
        stack.append((node, True))
        stack.extend((child, False) for child in children if id(child) not in size)


def _children(node: yaml.Node) -> list[yaml.Node]:
    if isinstance(node, yaml.MappingNode):
        return [part for pair in node.value for part in pair]
    if isinstance(node, yaml.SequenceNode):
        return list(node.value)
    return []


def _first_line(exc: Exception) -> str:
    """The parser's message without the context lines it adds (one problem, one line)."""
    return (str(exc).strip().splitlines() or [type(exc).__name__])[0]


def _walk(node: yaml.Node, path: Path_, lines: dict, key_lines: dict) -> None:
    lines[path] = node.start_mark.line + 1
    if isinstance(node, yaml.MappingNode):
        for key_node, value_node in node.value:
            key = (
                yaml.safe_load(yaml.serialize(key_node))
                if not isinstance(key_node, yaml.ScalarNode)
                else key_node.value
            )
            child = path + (key,)
            key_lines[child] = key_node.start_mark.line + 1
            _walk(value_node, child, lines, key_lines)
    elif isinstance(node, yaml.SequenceNode):
        for index, item in enumerate(node.value):
            _walk(item, path + (index,), lines, key_lines)
