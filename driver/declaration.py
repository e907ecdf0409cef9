"""How a declared option (``driver/options.py``) becomes a command-line flag with its help,
a key of a trainer config's run-level sections (``env_settings``, ``checkpoint_settings``,
``debug``, as mlagents-learn reads them), and a check with a one-line error.

As in mlagents-learn, a value given on the command line wins over the trainer config's,
which wins over the default; the options remember which ones the command line gave."""

from __future__ import annotations

import argparse
import dataclasses
import difflib
import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any, TypeVar, get_args, get_origin, get_type_hints

Check = Callable[[Any], str | None]  # a problem with the value, or None
GIVEN = "given"  # the field of an options class naming what the command line gave


class TrainingError(Exception):
    """A one-line problem with the run's options, found before anything starts."""


@dataclass(frozen=True)
class Option:
    help: str
    parse: Callable[[str], Any] | None = None  # text -> value (default: the field's type)
    check: Check | None = None
    aliases: tuple[str, ...] = ()  # more flags for it (mlagents-learn's names among them)
    negative: str | None = None  # a True default switched off by this flag
    yaml: tuple[str, ...] = ()  # "section.key" of a trainer config that may set it
    positional: str | None = None  # also taken as this positional argument
    rest: bool = False  # takes every argument after its flag (mlagents-learn's --env-args)
    hidden: bool = False  # accepted, not shown (mlagents-learn's deprecated and removed ones)


def option(default: Any, help: str, **how: Any) -> Any:
    if isinstance(how.get("yaml"), str):
        how["yaml"] = (how["yaml"],)
    return field(default=default, metadata={"option": Option(help, **how)})


def given_field() -> Any:
    """The names of the options the command line gave (not an option itself)."""
    return field(default=frozenset(), repr=False, compare=False)


def flag(name: str) -> str:
    return "--" + name.replace("_", "-")


def declared(kind: Any) -> list[tuple[dataclasses.Field[Any], Option]]:
    return [(f, f.metadata["option"]) for f in dataclasses.fields(kind) if "option" in f.metadata]


# ---- checks -----------------------------------------------------------------------------


def at_least(low: float) -> Check:
    def check(value: Any) -> str | None:
        return None if value is None or value >= low else f"at least {low:g}, got {value:g}"

    return check


def positive(value: Any) -> str | None:
    if value is None or (math.isfinite(value) and value > 0):
        return None
    return f"positive, got {value:g}"


def one_path_component(value: str | None) -> str | None:
    """A run id names one directory inside the results directory, never a path."""
    if value is not None and (value in ("", ".", "..") or any(c in value for c in "/\\\0")):
        return f"one directory name (no '/', not '.' or '..'), got {value!r}"
    return None


def check_fields(options: Any) -> None:
    for item, how in declared(options):
        if how.check and (problem := how.check(getattr(options, item.name))):
            raise TrainingError(f"{flag(item.name)}: {problem}")


# ---- the command line -------------------------------------------------------------------


def _scalar(annotation: Any) -> type:
    """int for ``int | None``, tuple for an argument list; str for the rest."""
    if get_origin(annotation) is tuple:
        return tuple
    first = (get_args(annotation) or (annotation,))[0]
    return first if first in (bool, int, float) else str


class _Given(argparse.Action):
    """Stores an option's value (a flag's constant) and notes that the command line gave it,
    so that a trainer config's value gives way only to what was given."""

    def __call__(
        self,
        parser: argparse.ArgumentParser,
        namespace: argparse.Namespace,
        values: Any,
        option_string: str | None = None,
    ) -> None:
        setattr(namespace, self.dest, self.const if self.nargs == 0 else values)
        setattr(namespace, GIVEN, getattr(namespace, GIVEN, frozenset()) | {self.dest})


def add_arguments(parser: argparse.ArgumentParser, kind: type) -> None:
    """Every option as a flag (its default in its help), and its positional form."""
    hints = get_type_hints(kind)
    for item, how in declared(kind):
        default, help = item.default, argparse.SUPPRESS if how.hidden else how.help
        if how.positional:  # absent, it stays out of the parsed arguments
            parser.add_argument(
                how.positional, nargs="?", default=argparse.SUPPRESS, help=help, action=_Given
            )
        scalar = _scalar(hints[item.name])
        names = (flag(item.name), *how.aliases)
        if how.negative or scalar is bool:  # a switch: no value follows
            switch = (how.negative,) if how.negative else names
            parser.add_argument(
                *switch,
                dest=item.name,
                action=_Given,
                nargs=0,
                const=not how.negative,
                default=default,
                help=help,
            )
        elif how.rest:
            parser.add_argument(
                *names,
                dest=item.name,
                action=_Given,
                nargs=argparse.REMAINDER,
                default=default,
                help=help,
            )
        else:
            if default not in (None, ()) and not how.hidden:
                help = f"{help} (default: {default})"
            parse = how.parse or scalar
            parser.add_argument(
                *names, dest=item.name, action=_Given, type=parse, default=default, help=help
            )


Options = TypeVar("Options")


def from_arguments(kind: type[Options], arguments: argparse.Namespace) -> Options:
    """The options a command line gave over the defaults, checked (TrainingError on the
    first problem), remembering which it gave."""
    values = dict(vars(arguments))
    given = set(values.get(GIVEN, ()))
    for item, how in declared(kind):
        if how.positional and how.positional in values:
            if item.name in given:
                raise TrainingError(f"{flag(item.name)}: given twice, as {how.positional} too")
            values[item.name] = values.pop(how.positional)
            given |= {item.name}
        if how.rest:
            values[item.name] = tuple(values[item.name])
    names = {item.name for item, _ in declared(kind)}
    options = kind(**{name: values[name] for name in names}, **{GIVEN: frozenset(given & names)})
    return options.validate()  # type: ignore[attr-defined,no-any-return]


# ---- a trainer config's run-level sections ----------------------------------------------


def run_level_keys(kind: type) -> dict[str, set[str]]:
    """Per section (or "" for top-level keys), the keys the options take from it."""
    keys: dict[str, set[str]] = {}
    for _, how in declared(kind):
        for path in how.yaml:
            section, _, key = path.rpartition(".")
            keys.setdefault(section, set()).add(key)
    return keys


def from_settings(options: Options, settings: Mapping[str, Any], source: str) -> Options:
    """The options with the values a trainer config's run-level sections give for what the
    command line did not; an unknown key or a bad value is one line naming it."""
    kind = type(options)
    known = run_level_keys(kind)
    for section, values in settings.items():
        if section in known and isinstance(values, Mapping):
            for key in values:
                if key not in known[section]:
                    close = difflib.get_close_matches(str(key), sorted(known[section]), 1)
                    hint = f"; did you mean {close[0]!r}?" if close else ""
                    raise TrainingError(f"{source}: {section}.{key}: unknown key{hint}")
        elif section in known:
            raise TrainingError(f"{source}: {section}: expected a mapping, got {values!r}")
    hints = get_type_hints(kind)
    changes: dict[str, Any] = {}
    for item, how in declared(kind):
        if item.name in getattr(options, GIVEN):
            continue
        for path in how.yaml:
            section, _, key = path.rpartition(".")
            values = settings.get(section, {}) if section else settings
            if key in values and values[key] is not None:
                changes[item.name] = _typed(values[key], hints[item.name], how, f"{source}: {path}")
    return dataclasses.replace(options, **changes) if changes else options  # type: ignore[type-var]


def _typed(value: Any, annotation: Any, how: Option, where: str) -> Any:
    """A YAML value as the option's type: what its parser makes of the text, where it has
    one; a list of strings for an argument list."""
    scalar = _scalar(annotation)
    if scalar is tuple:
        if isinstance(value, str):
            value = value.split()
        if not isinstance(value, list) or not all(isinstance(v, str | int | float) for v in value):
            raise TrainingError(f"{where}: expected a list of arguments, got {value!r}")
        return tuple(str(v) for v in value)
    if scalar is bool:
        if not isinstance(value, bool):
            raise TrainingError(f"{where}: expected true or false, got {value!r}")
        return value
    try:
        if how.parse is not None:
            return how.parse(str(value))
        if isinstance(value, bool) or (scalar is int and isinstance(value, float)):
            raise ValueError
        return scalar(value)
    except (ValueError, argparse.ArgumentTypeError) as error:
        raise TrainingError(
            f"{where}: expected {scalar.__name__}, got {value!r}{_why(error)}"
        ) from None


def _why(error: Exception) -> str:
    return f" ({error})" if isinstance(error, argparse.ArgumentTypeError) else ""
