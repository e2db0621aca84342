"""Command-line options generated from typed config dataclasses (one source of defaults).

Each field becomes ``--field-name``; a nested dataclass field ``policy``
contributes ``--policy-<name>`` options. Help texts are the attribute
docstrings written under each field.
"""

from __future__ import annotations

import argparse
import ast
import dataclasses
import inspect
import math
import numbers
import textwrap
import typing


class CommandLineParser(argparse.ArgumentParser):
    """``argparse.ArgumentParser`` as every tool of the project uses it: options are never abbreviated
    (``--total-timestep`` is refused, not taken for ``--total-timesteps``), and an error is one line,
    ``prog: error: message``, and a hint ``see prog --help``, not the usage block. Subcommands' parsers
    (``add_subparsers``) are of this class too."""

    def __init__(self, *args, **kwargs):
        kwargs.setdefault("allow_abbrev", False)
        super().__init__(*args, **kwargs)

    def error(self, message: str):
        self.exit(2, f"{self.prog}: error: {message}\nsee {self.prog} --help\n")


class DefaultsHelpFormatter(argparse.RawDescriptionHelpFormatter):
    """Help with each option's default shown (``(default: X)``) unless its help shows it already, it has none
    (None, a required option, a flag) or it is positional; the description kept as written."""

    def _get_help_string(self, action):
        text = action.help or ""
        if (
            "%(default)" in text
            or "(default:" in text
            or action.default in (None, argparse.SUPPRESS)
            or action.required
            or action.nargs == 0
            or not action.option_strings
        ):
            return text
        return f"{text} (default: {action.default!r})" if action.default == "" else f"{text} (default: %(default)s)"


def field_docs(cls) -> dict[str, str]:
    """Attribute docstrings (a string literal right after a field) of a dataclass."""
    try:
        tree = ast.parse(textwrap.dedent(inspect.getsource(cls)))
    except (OSError, TypeError):
        return {}
    body = tree.body[0].body  # type: ignore[attr-defined]
    docs = {}
    for node, nxt in zip(body, body[1:], strict=False):
        if (
            isinstance(node, ast.AnnAssign)
            and isinstance(node.target, ast.Name)
            and isinstance(nxt, ast.Expr)
            and isinstance(nxt.value, ast.Constant)
            and isinstance(nxt.value.value, str)
        ):
            docs[node.target.id] = " ".join(nxt.value.value.split())
    return docs


def parse_bool(text: str) -> bool:
    value = text.strip().lower()
    if value in ("1", "true", "yes", "on"):
        return True
    if value in ("0", "false", "no", "off"):
        return False
    raise argparse.ArgumentTypeError(f"expected true/false, got {text!r}")


def add_dataclass_options(parser: argparse.ArgumentParser, cls, prefix: str = "", skip=(), defaults=None) -> None:
    """Add one option per field; defaults are left to the dataclass (argparse default: None). ``defaults``, an
    instance of ``cls``, is what the help shows as defaults when a tool starts from other values than the
    class's own."""
    hints = typing.get_type_hints(cls)
    docs = field_docs(cls)
    for f in dataclasses.fields(cls):
        if f.name in skip:
            continue
        kind = hints[f.name]
        if dataclasses.is_dataclass(kind):
            sub = None if defaults is None else getattr(defaults, f.name)
            add_dataclass_options(parser, kind, prefix=f"{prefix}{f.name}-", defaults=sub)
            continue
        if defaults is not None:
            default = getattr(defaults, f.name)
        else:
            default = f.default if f.default is not dataclasses.MISSING else f.default_factory()
        conv = parse_bool if kind is bool else kind
        parser.add_argument(
            f"--{prefix}{f.name}".replace("_", "-"),
            dest=f"{prefix}{f.name}".replace("-", "__"),
            type=conv,
            default=None,
            metavar=kind.__name__.upper(),
            help=f"{docs.get(f.name, '')} (default: {default})",
        )


def overrides_from_args(args: argparse.Namespace, cls, prefix: str = "") -> dict:
    """Nested dict of the options given on the command line (None = not given)."""
    hints = typing.get_type_hints(cls)
    out: dict = {}
    for f in dataclasses.fields(cls):
        kind = hints[f.name]
        if dataclasses.is_dataclass(kind):
            sub = overrides_from_args(args, kind, prefix=f"{prefix}{f.name}__")
            if sub:
                out[f.name] = sub
            continue
        value = getattr(args, f"{prefix}{f.name}", None)
        if value is not None:
            out[f.name] = value
    return out


def replace_nested(obj, overrides: dict):
    """dataclasses.replace that also descends into nested dataclass fields."""
    changes = {}
    for key, value in overrides.items():
        current = getattr(obj, key)
        changes[key] = replace_nested(current, value) if dataclasses.is_dataclass(current) else value
    return dataclasses.replace(obj, **changes)


def check_field_types(obj) -> None:
    """Raise ``TypeError`` naming the field when a value does not have its field's type (bool, int, float or
    str; an int is a float, a bool is neither an int nor a float), or a float is NaN: a hand-edited JSON
    config ("learning_rate": "3e-4") fails here, before anything runs, not deep inside training."""
    hints = typing.get_type_hints(type(obj))
    for f in dataclasses.fields(obj):
        kind, value = hints[f.name], getattr(obj, f.name)
        if kind not in (bool, int, float, str):
            continue
        if kind is bool or kind is str:
            ok = isinstance(value, kind)
        else:  # int or float: never a bool; an int is a float too
            ok = not isinstance(value, bool) and isinstance(value, numbers.Real if kind is float else numbers.Integral)
        if not ok:
            raise TypeError(f"{f.name} must be {kind.__name__}, got {type(value).__name__} {value!r}")
        if kind is float and math.isnan(value):
            raise TypeError(f"{f.name} must be a number, got NaN")
