"""MkDocs hook: reference pages generated from the code at build time.

The configuration reference comes from the pydantic schema in ``gateway/config.py``
and the CLI reference from the click command tree in ``gateway/cli/main.py``, so neither
can drift from the code. The edge-box walkthrough is ``deploy/README.md`` itself
(kept beside the compose files it describes), published as a manual page.
"""

from __future__ import annotations

import inspect
import io
import re
import tokenize
import types
import typing
from pathlib import Path

import annotated_types
import click
from mkdocs.config.defaults import MkDocsConfig
from mkdocs.structure.files import File, Files
from pydantic import BaseModel
from pydantic.fields import FieldInfo
from pydantic_core import PydanticUndefined

ROOT = Path(__file__).resolve().parents[2]

_BOUNDS = (
    (annotated_types.Gt, "gt", "> {}"),
    (annotated_types.Ge, "ge", "≥ {}"),
    (annotated_types.Lt, "lt", "< {}"),
    (annotated_types.Le, "le", "≤ {}"),
    (annotated_types.MinLen, "min_length", "at least {} item(s)"),
    (annotated_types.MaxLen, "max_length", "at most {} item(s)"),
)


# ---------------------------------------------------------------- configuration


def _cell(text: str) -> str:
    """Text safe inside one Markdown table cell."""
    return " ".join(str(text).split()).replace("|", "\\|")


def type_name(tp: object) -> str:
    """A short, readable name for a field's annotation."""
    origin = typing.get_origin(tp)
    args = typing.get_args(tp)
    if origin is typing.Literal:
        return " \\| ".join(repr(a) for a in args)
    if origin in (typing.Union, types.UnionType):
        return " \\| ".join(type_name(a) for a in args)
    if origin is typing.Annotated:
        return type_name(args[0])
    if origin is not None:
        inner = ", ".join(type_name(a) for a in args)
        return f"{getattr(origin, '__name__', str(origin))}[{inner}]"
    if tp is type(None):
        return "null"
    if tp is typing.Any:
        return "any"
    return getattr(tp, "__name__", str(tp).replace("typing.", ""))


def nested_models(tp: object) -> list[type[BaseModel]]:
    """The pydantic models inside an annotation (``X``, ``list[X]``, ``X | None`` …)."""
    if isinstance(tp, type) and issubclass(tp, BaseModel):
        return [tp]
    found: list[type[BaseModel]] = []
    for arg in typing.get_args(tp):
        found.extend(m for m in nested_models(arg) if m not in found)
    return found


def holds_list(tp: object) -> bool:
    """Whether the annotation is a list (possibly optional): its path gets ``[]``."""
    if typing.get_origin(tp) is list:
        return True
    return typing.get_origin(tp) in (typing.Union, types.UnionType) and any(
        typing.get_origin(a) is list for a in typing.get_args(tp)
    )


def default_text(field: FieldInfo) -> str:
    """The default as YAML would spell it, or *required*."""
    if field.default_factory is not None:
        value = field.default_factory()  # type: ignore[call-arg]
    elif field.default is PydanticUndefined:
        return "**required**"
    else:
        value = field.default
    if isinstance(value, BaseModel):
        return "(section defaults)"
    if value is None:
        return "null"
    if isinstance(value, bool):
        return str(value).lower()
    return f"`{value}`" if str(value) != "" else '`""`'


def constraints_text(field: FieldInfo) -> str:
    """Bounds and patterns pydantic enforces on the field."""
    parts = []
    for meta in field.metadata:
        for kind, attr, fmt in _BOUNDS:
            if isinstance(meta, kind):
                parts.append(fmt.format(getattr(meta, attr)))
        pattern = getattr(meta, "pattern", None)
        if pattern:
            parts.append(f"matches `{pattern}`")
        if getattr(meta, "allow_inf_nan", None) is False:
            parts.append("finite")
    return ", ".join(parts)


def source_comments(model: type[BaseModel]) -> dict[str, str]:
    """Trailing ``# comments`` on each field line of the model's source."""
    try:
        source = inspect.getsource(model)
    except (OSError, TypeError):
        return {}
    comments: dict[str, str] = {}
    lines = source.splitlines()
    for tok in tokenize.generate_tokens(io.StringIO(source).readline):
        if tok.type != tokenize.COMMENT:
            continue
        line = lines[tok.start[0] - 1]
        match = re.match(r"\s+(\w+)\s*:", line)
        if match and line.strip()[0] != "#":
            text = TOOL_DIRECTIVE.split(tok.string, maxsplit=1)[0]
            comments[match.group(1)] = text.lstrip("# ").strip()
    return comments


#: Where a comment turns into an instruction to a type checker, linter or formatter
#: (type-ignore, noqa, pragma, fmt markers): for tools, not for the reader of the reference.
TOOL_DIRECTIVE = re.compile(r"#\s*(?:type:|noqa\b|pragma\b|fmt:)")


def field_row(name: str, field: FieldInfo, comments: dict[str, str]) -> str:
    description = field.description or comments.get(name, "")
    limits = constraints_text(field)
    if limits:
        description = f"{description} ({limits})" if description else limits
    key = field.alias or name
    return (
        f"| `{key}` | {type_name(field.annotation)} | {_cell(default_text(field))} "
        f"| {_cell(description)} |"
    )


def section_markdown(path: str, model: type[BaseModel]) -> list[str]:
    """One section: its docstring and a table of its keys."""
    out = [f"## `{path}`", ""]
    own_doc = model.__dict__.get("__doc__")  # not a base class's
    if own_doc:
        out += [inspect.cleandoc(own_doc), ""]
    out += ["| key | type | default | description |", "|---|---|---|---|"]
    comments = source_comments(model)
    for name, field in model.model_fields.items():
        out.append(field_row(name, field, comments))
    return [*out, ""]


def walk_sections(path: str, model: type[BaseModel], seen: set[str]) -> list[str]:
    """The section and, after it, every section nested in it (depth first)."""
    if path in seen:
        return []
    seen.add(path)
    out = section_markdown(path, model)
    for name, field in model.model_fields.items():
        key = field.alias or name
        suffix = "[]" if holds_list(field.annotation) else ""
        for child in nested_models(field.annotation):
            out += walk_sections(f"{path}.{key}{suffix}".lstrip("."), child, seen)
    return out


def configuration_page() -> str:
    from gateway.config import GatewayConfig

    head = [
        "# Configuration reference",
        "",
        "Generated from the pydantic schema in `gateway/config.py` when the manual is built:",
        "every section, key, type, default and limit the gateway enforces. Keys are",
        "strict: an unknown key is refused with its file, line and column.",
        "",
        "Editors that speak the YAML language server validate `config.yaml` against",
        "`docs/config.schema.json` (generated from the same schema) when the file's",
        "first line is:",
        "",
        "```yaml",
        "# yaml-language-server: $schema=docs/config.schema.json",
        "```",
        "",
        "Regenerate the schema file after changing `gateway/config.py`:",
        "`.venv/bin/python -m gateway.config_schema > docs/config.schema.json`",
        "(`tests/test_docs.py` fails while it is stale).",
        "",
    ]
    body = walk_sections("", GatewayConfig, set())
    body[0] = "## Top level"
    return "\n".join(head + body)


# ---------------------------------------------------------------- CLI


def shown_default(param: click.Parameter, ctx: click.Context) -> str:
    """The option's default, or nothing when it has none (``None``, empty, click's UNSET)."""
    default = param.get_default(ctx, call=False)
    if default is None or default == () or type(default).__name__ == "Sentinel":
        return ""
    if callable(default):
        return "(computed)"
    return str(default)


def option_row(param: click.Parameter, ctx: click.Context) -> str:
    names = ", ".join(f"`{n}`" for n in param.opts + param.secondary_opts)
    kind = "flag" if getattr(param, "is_flag", False) else param.type.name
    if isinstance(param.type, click.Choice):
        kind = " | ".join(str(c) for c in param.type.choices)
    shown = "**required**" if param.required else shown_default(param, ctx)
    if getattr(param, "multiple", False):
        kind += " (repeatable)"
    helptext = getattr(param, "help", "") or ""
    return f"| {names} | {_cell(kind)} | {_cell(shown)} | {_cell(helptext)} |"


def command_markdown(cmd: click.Command, ctx: click.Context, depth: int) -> list[str]:
    out = [f"{'#' * depth} `{ctx.command_path}`", ""]
    out += ["```text", cmd.get_usage(ctx), "```", ""]
    if cmd.help:
        out += [inspect.cleandoc(cmd.help).replace("\b\n", ""), ""]
    options = [p for p in cmd.get_params(ctx) if isinstance(p, click.Option)]
    if options:
        out += ["| option | type | default | help |", "|---|---|---|---|"]
        out += [option_row(p, ctx) for p in options]
        out.append("")
    return out


def walk_commands(cmd: click.Command, ctx: click.Context, depth: int) -> list[str]:
    out = command_markdown(cmd, ctx, depth)
    if isinstance(cmd, click.Group):
        for name in cmd.list_commands(ctx):
            sub = cmd.get_command(ctx, name)
            if sub is not None and not sub.hidden:
                child = click.Context(sub, info_name=name, parent=ctx)
                out += walk_commands(sub, child, min(depth + 1, 6))
    return out


def cli_page() -> str:
    from gateway.cli.main import main

    head = [
        "# CLI reference",
        "",
        "Generated from the click command tree in `gateway/cli/main.py` when the manual is",
        "built. Run every command from the repository root as",
        "`.venv/bin/python -m gateway …`; `--help` on any command prints the same text.",
        "",
    ]
    ctx = click.Context(main, info_name="python -m gateway")
    return "\n".join(head + walk_commands(main, ctx, 2))


# ---------------------------------------------------------------- edge box


def edge_box_page() -> str:
    """``deploy/README.md`` as it is: one text for the repository and the manual."""
    return (ROOT / "deploy" / "README.md").read_text(encoding="utf-8")


GENERATED = {
    "configuration.md": configuration_page,
    "cli.md": cli_page,
    "deployment/edge-box.md": edge_box_page,
}


def on_files(files: Files, config: MkDocsConfig) -> Files:
    """Add the generated pages to the build (they exist only in the site)."""
    for uri, make in GENERATED.items():
        files.append(File.generated(config, uri, content=make()))
    return files
