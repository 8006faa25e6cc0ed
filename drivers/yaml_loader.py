"""One YAML loader for every file people edit: line numbers, and no silent surprises.

Configuration files, the simulator's machine parameters and its speed
programmes are all read here, so they are all refused the same way, with the
file and the line: ``config.yaml:23: machines[0].compensation.clamp_um: …``.

What plain ``yaml.safe_load`` lets through, and this loader refuses:

- a key given twice in one mapping (YAML keeps the last one without a word);
- more than :data:`MAX_ALIASES` aliases, or more than :data:`MAX_VALUES` values
  once aliases are expanded (a few kilobytes of nested aliases otherwise grow
  to gigabytes: the "billion laughs");
- a file over :data:`MAX_BYTES`, a directory, a binary file, bytes that are not
  UTF-8 (the line and column of the first bad byte are named);
- ``.inf`` and ``.nan``: no setting of a machine tool is infinite.

:func:`validate` checks a loaded section against a pydantic schema and turns
the first problem into one located line. A validator that checks one key
from a wider view (a model validator comparing two keys) raises
:class:`KeyPathError` naming that key, so the message points at its line.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, TypeVar

import yaml
from pydantic import BaseModel, ValidationError
from yaml.composer import Composer

#: PyYAML built without libyaml takes the Python path for every file.
HAVE_LIBYAML = yaml.__with_libyaml__
CSafeLoader = yaml.CSafeLoader if HAVE_LIBYAML else yaml.SafeLoader

MAX_BYTES = 1_000_000
"""Largest file read: a configuration of many machines is a few tens of kilobytes."""
MAX_ALIASES = 100
"""Most aliases (``*name``) in one file; hand-written files use a few, if any."""
MAX_VALUES = 100_000
"""Most values (keys, scalars, lists) once aliases are expanded."""

Loc = tuple[str | int, ...]
Model = TypeVar("Model", bound=BaseModel)

_FLOAT_TAG = "tag:yaml.org,2002:float"
_MERGE_TAG = "tag:yaml.org,2002:merge"
_STR_TAG = "tag:yaml.org,2002:str"


class YamlError(ValueError):
    """A file that cannot be used, located: ``file:line: key.path: what was expected``."""


class ReferencedFileError(Exception):
    """A file that the document being validated names (a register map) is bad.

    Not a ``ValueError``, so pydantic does not fold it into the naming document's
    errors: :func:`validate` re-raises the other file's own located error.
    """

    def __init__(self, error: YamlError) -> None:
        super().__init__(str(error))
        self.error = error


class KeyPathError(ValueError):
    """Raised by a validator to blame ``key`` (a path below the object it validates)."""

    def __init__(self, key: Sequence[str | int], message: str) -> None:
        super().__init__(message)
        self.key: Loc = tuple(key)


def format_path(loc: Loc) -> str:
    """``machines[0].cnc.opcua`` from ``("machines", 0, "cnc", "opcua")``."""
    text = ""
    for part in loc:
        text += f"[{part}]" if isinstance(part, int) else (f".{part}" if text else str(part))
    return text or "(top level)"


@dataclass(frozen=True)
class YamlDocument:
    """The data of one file, and the line of every key path in it."""

    path: Path
    data: Any
    lines: dict[Loc, int]

    def line_of(self, loc: Loc) -> int | None:
        """The line of the deepest part of ``loc`` the file has (a default has none)."""
        for depth in range(len(loc), -1, -1):
            if loc[:depth] in self.lines:
                return self.lines[loc[:depth]]
        return None

    def locate(self, loc: Loc) -> str:
        """``file:line: key.path``."""
        line = self.line_of(loc)
        where = f"{self.path}:{line}" if line is not None else str(self.path)
        return f"{where}: {format_path(loc)}"

    def error(self, loc: Loc, message: str) -> YamlError:
        return YamlError(f"{self.locate(loc)}: {message}")

    def section(self, loc: Loc) -> Any:
        """The data at ``loc`` (``None`` if the file does not have it)."""
        value = self.data
        for part in loc:
            try:
                value = value[part]
            except (KeyError, IndexError, TypeError):
                return None
        return value


class _AliasCounting(Composer):
    """Counts aliases while it composes, so a bomb stops early (with the alias's line)."""

    aliases = 0

    if TYPE_CHECKING:  # the parser's, which every loader this is mixed into has

        def check_event(self, *choices: Any) -> bool: ...
        def peek_event(self) -> Any: ...

    def compose_node(self, parent: yaml.Node | None, index: int) -> yaml.Node | None:
        if self.check_event(yaml.AliasEvent):
            self.aliases += 1
            if self.aliases > MAX_ALIASES:
                line = self.peek_event().start_mark.line + 1
                raise _RefusedError(line, f"more than {MAX_ALIASES} YAML aliases (*name)")
        return super().compose_node(parent, index)


class _Loader(_AliasCounting, yaml.SafeLoader):
    """The pure-Python reader, scanner and parser: the messages every located error quotes."""


class _FastLoader(_AliasCounting, CSafeLoader):  # type: ignore[misc, valid-type]
    """libyaml's scanner and parser under the same Python composer (recursion-limited).

    libyaml's own composer recurses in C (a deeply nested file crashes the
    process) and words its errors differently, so only its events are used, and
    a file it cannot read is read again by :class:`_Loader` for the message.
    """

    def __init__(self, stream: str) -> None:
        CSafeLoader.__init__(self, stream)
        self.anchors: dict[Any, yaml.Node] = {}


class _RefusedError(Exception):
    """A problem found while walking the document, with its line and key path."""

    def __init__(self, line: int, message: str, loc: Loc | None = None) -> None:
        super().__init__(message)
        self.line = line
        self.message = message
        self.loc = loc


def load_yaml(path: str | Path) -> YamlDocument:
    """Read, check and parse one YAML file; any problem is a located :class:`YamlError`.

    A good file is parsed by libyaml (a 36,000-line configuration in about a
    second instead of two and a half); a file with any problem is parsed again by
    the pure-Python parser, whose located message is the one reported.
    """
    path = Path(path)
    text = _read_text(path)
    document = _load_fast(path, text)
    return document if document is not None else _load_checked(path, text)


def _load_fast(path: Path, text: str) -> YamlDocument | None:
    """The document through libyaml's parser, or ``None`` on any problem (or no libyaml)."""
    if not HAVE_LIBYAML or yaml.reader.Reader.NON_PRINTABLE.search(text):
        return None  # the Python reader refuses characters libyaml lets through
    try:
        loader = _FastLoader(text)
    except yaml.YAMLError:
        return None
    try:
        return _compose_and_construct(path, loader)
    except (_RefusedError, yaml.YAMLError, RecursionError):
        return None
    finally:
        loader.dispose()


def _compose_and_construct(path: Path, loader: Any) -> YamlDocument:
    root = loader.get_single_node()
    lines: dict[Loc, int] = {}
    if root is not None:
        _Walker(loader, lines).walk(root, ())
    data = None if root is None else loader.construct_document(root)
    return YamlDocument(path, data, lines)


def _load_checked(path: Path, text: str) -> YamlDocument:
    """The pure-Python parse, which turns every problem into a located :class:`YamlError`."""
    try:
        loader = _Loader(text)
    except yaml.reader.ReaderError as exc:
        raise _unprintable(path, text, exc) from None
    try:
        return _compose_and_construct(path, loader)
    except _RefusedError as exc:
        where = f" {format_path(exc.loc)}:" if exc.loc is not None else ""
        raise YamlError(f"{path}:{exc.line}:{where} {exc.message}") from None
    except yaml.MarkedYAMLError as exc:
        mark = exc.problem_mark or exc.context_mark
        where = f"{path}:{mark.line + 1}" if mark is not None else str(path)
        problem = exc.problem or exc.context or "not valid YAML"
        raise YamlError(f"{where}: not valid YAML ({problem})") from None
    except yaml.reader.ReaderError as exc:
        raise _unprintable(path, text, exc) from None
    except RecursionError:
        line = loader.line + 1
        raise YamlError(f"{path}:{line}: nested too deeply to be a configuration") from None
    finally:
        loader.dispose()


def _unprintable(path: Path, text: str, exc: yaml.reader.ReaderError) -> YamlError:
    line = text.count("\n", 0, exc.position) + 1
    code = exc.character if isinstance(exc.character, int) else ord(exc.character)
    return YamlError(f"{path}:{line}: control character U+{code:04X} is not allowed in YAML")


def _read_text(path: Path) -> str:
    try:
        if path.is_dir():
            raise YamlError(f"{path}: is a directory; a YAML file was expected")
        size = path.stat().st_size
        if size > MAX_BYTES:
            raise YamlError(
                f"{path}: {size} bytes, larger than any sane configuration "
                f"(at most {MAX_BYTES} bytes)"
            )
        with path.open("rb") as handle:
            data = handle.read(MAX_BYTES + 1)
    except FileNotFoundError:
        raise YamlError(f"{path}: no such file") from None
    except OSError as exc:
        raise YamlError(f"{path}: cannot be read ({exc.strerror or exc})") from None
    if len(data) > MAX_BYTES:
        raise YamlError(f"{path}: larger than any sane configuration (at most {MAX_BYTES} bytes)")
    nul = data.find(b"\x00")
    if nul >= 0:
        line, column = _line_column(data, nul)
        raise YamlError(f"{path}:{line}: a NUL byte at column {column}: a binary file, not YAML")
    try:
        return data.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        line, column = _line_column(data, exc.start)
        byte = data[exc.start]
        raise YamlError(
            f"{path}:{line}: byte 0x{byte:02x} at column {column} is not UTF-8 "
            "(save the file as UTF-8)"
        ) from None


def _line_column(data: bytes, offset: int) -> tuple[int, int]:
    line = data.count(b"\n", 0, offset) + 1
    column = offset - (data.rfind(b"\n", 0, offset) + 1) + 1
    return line, column


class _Walker:
    """Records key lines and refuses duplicate keys, non-finite numbers and alias growth."""

    def __init__(self, loader: Any, lines: dict[Loc, int]) -> None:
        self.loader = loader
        self.lines = lines
        self.values = 0
        self.open: set[int] = set()

    def walk(self, node: yaml.Node, loc: Loc) -> None:
        self.values += 1
        line = node.start_mark.line + 1
        if self.values > MAX_VALUES:
            raise _RefusedError(line, f"aliases expand to more than {MAX_VALUES} values")
        if id(node) in self.open:
            raise _RefusedError(line, "an alias refers to the value that contains it", loc)
        self.lines.setdefault(loc, line)
        if isinstance(node, yaml.ScalarNode):
            self._finite(node, loc)
            return
        self.open.add(id(node))
        if isinstance(node, yaml.MappingNode):
            self._mapping(node, loc)
        elif isinstance(node, yaml.SequenceNode):
            for index, item in enumerate(node.value):
                self.walk(item, (*loc, index))
        self.open.discard(id(node))

    def _mapping(self, node: yaml.MappingNode, loc: Loc) -> None:
        seen: dict[tuple[str, str], int] = {}
        for key, value in node.value:
            line = key.start_mark.line + 1
            if not isinstance(key, yaml.ScalarNode):
                self.walk(value, loc)
                continue
            if key.tag == _MERGE_TAG:
                self.walk(value, loc)  # a merge: its keys may be overridden here
                continue
            name = key.value if key.tag == _STR_TAG else self.loader.construct_object(key)
            child = (*loc, name)
            identity = (key.tag, key.value)
            if identity in seen:
                raise _RefusedError(
                    line,
                    f"key given twice (lines {seen[identity]} and {line}); "
                    "YAML would silently keep the last, remove one",
                    child,
                )
            seen[identity] = line
            self.lines[child] = line
            self.walk(value, child)

    def _finite(self, node: yaml.ScalarNode, loc: Loc) -> None:
        if node.tag == _FLOAT_TAG:
            value = self.loader.construct_yaml_float(node)
            if not math.isfinite(value):
                raise _RefusedError(
                    node.start_mark.line + 1,
                    f"{node.value} is not a finite number; a finite value was expected",
                    loc,
                )


def validate(document: YamlDocument, model: type[Model], section: Loc = ()) -> Model:
    """``model`` built from the data at ``section``; the first problem as a located error.

    Files the section names (register maps) are found relative to the document's folder.
    """
    try:
        return model.model_validate(
            document.section(section), context={"source_dir": document.path.parent}
        )
    except ReferencedFileError as exc:
        raise exc.error from None
    except ValidationError as exc:
        loc, message = first_problem(exc)
        raise document.error((*section, *loc), message) from None


def first_problem(exc: ValidationError) -> tuple[Loc, str]:
    """The key path and a plain message for the first error pydantic reports."""
    first = exc.errors()[0]
    loc: Loc = tuple(
        part
        for part in first["loc"]
        if not (isinstance(part, str) and part.startswith("function-"))
    )
    message = first["msg"].removeprefix("Value error, ")
    problem = (first.get("ctx") or {}).get("error")
    if isinstance(problem, KeyPathError):
        loc = (*loc, *problem.key)
        message = str(problem)
    elif first["type"] == "missing":
        message = "required key is missing"
    elif first["type"] == "extra_forbidden":
        message = "unknown key (not part of the configuration)"
    return loc, message
