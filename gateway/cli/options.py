"""What every command shares: option types, the bad-input exit, JSON output, skipped-row notes.

Imports only click and the standard library, so ``--help`` stays fast
(tests/test_cli_start.py).
"""

from __future__ import annotations

import math
import sys
from collections.abc import Callable, Sequence
from functools import wraps
from pathlib import Path
from typing import Any

import click

#: The project's input errors (``models.data.dataset.DataError``, ``models.store.StoreError``,
#: ``gateway.config.ConfigError``, …) are all ``ValueError``s, so catching the
#: built-in types catches them without importing the modules that define them at
#: start-up; tests/test_cli_start.py checks that each of them still is one.
INPUT_ERRORS = (ValueError, KeyError, OSError)


class FiniteFloatRange(click.FloatRange):
    """click's ``FloatRange`` that also refuses NaN and ±inf. The range check alone passes
    NaN (every comparison with it is false), and an infinite interval or speed-up reached
    integer conversions far from the option that carried it."""

    name = "finite float range"

    def convert(self, value: Any, param: click.Parameter | None, ctx: click.Context | None) -> Any:
        number = super().convert(value, param, ctx)
        if not math.isfinite(number):
            self.fail(f"{value!r} is not a finite number.", param, ctx)
        return number


def input_errors_exit(command: Callable[..., Any]) -> Callable[..., Any]:
    """Turn a bad-input exception into one clear line and exit status 2."""

    @wraps(command)
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        try:
            return command(*args, **kwargs)
        except INPUT_ERRORS as exc:
            message = exc.args[0] if isinstance(exc, KeyError) and exc.args else exc
            click.echo(f"error: {message}", err=True)
            sys.exit(2)

    return wrapper


def quantity_option(
    flag: str, default: float, help: str, *, name: str | None = None
) -> Callable[[Callable[..., Any]], Callable[..., Any]]:
    """A ``--flag`` taking a positive quantity in the unit its name ends with."""
    declarations = (flag,) if name is None else (flag, name)
    return click.option(
        *declarations,
        type=FiniteFloatRange(min=0, min_open=True),
        default=default,
        show_default=True,
        help=help,
    )


Decorator = Callable[[Callable[..., Any]], Callable[..., Any]]

#: The log levels ``run`` and ``demo`` take.
LOG_LEVELS = ("debug", "info", "warning", "error")


def config_option(**changes: Any) -> Decorator:
    """``--config``, the gateway's configuration file (``config.yaml`` unless changed;
    ``default=None``: none)."""
    settings: dict[str, Any] = {"type": click.Path(path_type=Path), "default": Path("config.yaml")}
    return click.option("--config", "config_path", **_given({**settings, **changes}))


def target_option(help: str = "Measured error column, µm.", **changes: Any) -> Decorator:
    """``--target``, the measured thermal-error column of a measured-run CSV (``default=None``:
    the command chooses)."""
    settings: dict[str, Any] = {"default": "error_um", "show_default": True, "help": help}
    settings.update(changes)
    if settings["default"] is None:
        settings["show_default"] = False
    return click.option("--target", **_given(settings))


def targets_option(
    help: str = "Measured error column, µm.", default: tuple[str, ...] | None = ("error_um",)
) -> Decorator:
    """``--target``, repeatable: the error columns an offline command works on, each in its
    own section (``all``: every error column of the file, a name ending in ``_um``)."""
    return click.option(
        "--target",
        "targets",
        multiple=True,
        default=default,
        show_default=default is not None,
        help=f"{help} Repeatable; 'all': every error column of the file (a name ending "
        "in _um), each target in its own section (JSON: a 'targets' object).",
    )


def _given(settings: dict[str, Any]) -> dict[str, Any]:
    """The settings but those given as None (click's own default then)."""
    return {key: value for key, value in settings.items() if value is not None}


def sensors_option(
    help: str = "Declared temperature inputs, e.g. T1,T7 (default: every T<n>).",
) -> Decorator:
    """``--sensors``, a comma-separated list of temperature columns (:func:`parse_sensors`)."""
    return click.option("--sensors", help=help)


def reference_option(policies: Sequence[str]) -> Decorator:
    """``--reference``, where rises are taken from (models/data/references.py)."""
    return click.option(
        "--reference",
        type=click.Choice(list(policies)),
        default="auto",
        show_default=True,
        help="Where rises are taken from (see models/data/references.py).",
    )


def json_option(help: str = "Write results as JSON.") -> Decorator:
    """``--json FILE``, the command's result as JSON (:func:`write_json`)."""
    return click.option("--json", "json_out", type=click.Path(path_type=Path), help=help)


def store_option(help: str, **changes: Any) -> Decorator:
    """``--store``, a model store folder."""
    return click.option(
        "--store", "store_dir", type=click.Path(path_type=Path), help=help, **changes
    )


def progress_option() -> Decorator:
    """``--progress/--no-progress``: progress bars, on a TTY unless said."""
    return click.option(
        "--progress/--no-progress", default=None, help="Progress bars (default: on a TTY)."
    )


def log_level_option(default: str) -> Decorator:
    """``--log-level``, the least level logged."""
    return click.option("--log-level", default=default, type=click.Choice(LOG_LEVELS))


def parse_sensors(value: str | None) -> list[str] | None:
    if value is None:
        return None
    names = [name.strip() for name in value.split(",") if name.strip()]
    if not names:
        raise click.BadParameter("expected sensor names such as T1,T7")
    return names


def write_json(path: Path | None, payload: dict[str, Any]) -> None:
    """A command's ``--json`` result, whole or not at all (a script may read it at once)."""
    if path is not None:
        from models.json_files import write_json_atomic

        write_json_atomic(path, payload)
        click.echo(f"wrote {path}")


def report_skipped(data) -> None:
    for skipped in data.skipped:
        click.echo(f"note: {skipped.describe()}", err=True)
    for note in data.notes:
        click.echo(f"note: {data.source}: {note}", err=True)
