"""Command-line options generated from typed config dataclasses (one source of defaults).

Each field becomes ``--field-name``; a nested dataclass field ``policy``
contributes ``--policy-<name>`` options. Help texts are the attribute
docstrings written under each field. A ``list[X]`` or ``tuple[X, ...]`` field
takes one or more values (``--namespaces a b``), an ``X | None`` field is
unset unless given; a field's ``metadata["metavar"]`` names its value.
"""

from __future__ import annotations

import argparse
import ast
import dataclasses
import inspect
import math
import numbers
import sys
import textwrap
import types
import typing
import warnings

BOOL_WORDS = ("true", "false", "1", "0", "yes", "no", "on", "off")
"""what a boolean option takes (any case)"""


class BoolAction(argparse.Action):
    """A boolean option, one style for every tool: ``--flag`` or ``--flag true`` is true, ``--flag false`` is
    false (``parse_bool``'s words). ``CommandLineParser`` makes the value explicit before parsing, so a flag
    alone never takes the next argument (a positional) for its value."""

    def __init__(self, option_strings, dest, default=None, required=False, help=None, metavar="BOOL"):
        super().__init__(option_strings, dest, nargs="?", const=True, default=default, type=parse_bool,
                         required=required, help=help, metavar=metavar)  # fmt: skip

    def __call__(self, parser, namespace, values, option_string=None):
        setattr(namespace, self.dest, values)


class DeprecatedAlias(argparse.Action):
    """An old spelling of an option, kept for a release: it sets what the new one sets (``value``: a fixed
    value, for ``--no-flag``) and says once, on stderr, how to write it now."""

    def __init__(self, option_strings, dest, new: str, value=None, nargs=None, **kwargs):
        self.new, self.value = new, value
        super().__init__(option_strings, dest, nargs=0 if value is not None else nargs, **kwargs)

    def __call__(self, parser, namespace, values, option_string=None):
        said = getattr(parser, "_deprecations_said", set())
        if option_string not in said:
            said.add(option_string)
            parser._deprecations_said = said
            print(f"{parser.prog}: warning: {option_string} is deprecated: write {self.new}", file=sys.stderr)
        setattr(namespace, self.dest, self.value if self.value is not None else values)


class CommandLineParser(argparse.ArgumentParser):
    """``argparse.ArgumentParser`` as every tool of the project uses it: options are never abbreviated
    (``--total-timestep`` is refused, not taken for ``--total-timesteps``), and an error is one line,
    ``prog: error: message``, and a hint ``see prog --help``, not the usage block. Booleans are
    ``BoolAction``s: ``--flag [true|false]``. Subcommands' parsers (``add_subparsers``) are of this class too."""

    def __init__(self, *args, **kwargs):
        kwargs.setdefault("allow_abbrev", False)
        super().__init__(*args, **kwargs)

    def error(self, message: str):
        self.exit(2, f"{self.prog}: error: {message}\nsee {self.prog} --help\n")

    def add_deprecated_alias(self, old: str, new: str, value=None, shown: str | None = None) -> None:
        """Accept ``old`` for the option ``new`` (with ``value``: ``old`` alone sets it, as ``--no-x`` sets
        ``--x false``), not shown in the help; ``shown``: how the warning writes the new form."""
        target = next(a for a in self._actions if new in a.option_strings)
        kwargs = {} if value is not None else {"nargs": target.nargs, "type": target.type, "metavar": target.metavar}
        self.add_argument(old, dest=target.dest, action=DeprecatedAlias, new=shown or new, value=value,
                          help=argparse.SUPPRESS, **kwargs)  # fmt: skip

    def parse_known_args(self, args=None, namespace=None):
        args = list(sys.argv[1:] if args is None else args)
        return super().parse_known_args(self._explicit_booleans(args), namespace)

    def _boolean_flags(self) -> set[str]:
        flags = set()
        for action in self._actions:
            if isinstance(action, BoolAction):
                flags.update(action.option_strings)
            elif isinstance(action, argparse._SubParsersAction):
                for sub in action.choices.values():
                    if isinstance(sub, CommandLineParser):
                        flags |= sub._boolean_flags()
        return flags

    def _explicit_booleans(self, args: list[str]) -> list[str]:
        """``--flag`` -> ``--flag=true``, ``--flag no`` -> ``--flag=no`` (up to ``--``)."""
        flags, out, i = self._boolean_flags(), [], 0
        while i < len(args):
            arg = args[i]
            if arg == "--":
                return out + args[i:]
            if arg in flags:
                following = args[i + 1] if i + 1 < len(args) else None
                if following is not None and following.strip().lower() in BOOL_WORDS:
                    arg, i = f"{arg}={following}", i + 1
                else:
                    arg = f"{arg}=true"
            out.append(arg)
            i += 1
        return out


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
    """Attribute docstrings (a string literal right after a field) of a dataclass, its base classes' included
    (``TrainConfig``'s fields come from its concerns, ``algo.config``: without them ``morph-train --bodies``
    had no help text); a class's own docstring of a field wins over a base's."""
    docs: dict[str, str] = {}
    for klass in reversed(cls.__mro__):
        if klass is not object and dataclasses.is_dataclass(klass):
            docs.update(_own_field_docs(klass))
    return docs


def _own_field_docs(cls) -> dict[str, str]:
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


def renamed_fields(**old_to_new: str):
    """A dataclass decorator for fields that were renamed: the constructor still takes each old name (with a
    ``DeprecationWarning``; silently when the new one is given too, with the same value, as ``to_dict`` writes
    both), an error about the field names the old one when the caller wrote it, and the old name reads the
    new field. ``add_dataclass_options`` adds the old options as deprecated aliases and ``overrides_from_args``
    maps them. Fields the class sets from others (``init=False``, listed in its ``derived``) are taken too
    when they agree, so that ``cls(**obj.to_dict())`` makes ``obj`` again. A subclass needs the decorator
    again (it gets a new ``__init__``)."""

    def wrap(cls):
        init = cls.__init__

        def __init__(self, *args, **kwargs):
            used = [old for old in old_to_new if old in kwargs]
            for old in used:
                new = old_to_new[old]
                if new not in kwargs:
                    warnings.warn(f"{cls.__name__}({old}=...) is deprecated: write {new}", DeprecationWarning,
                                  stacklevel=2)  # fmt: skip
                elif kwargs[new] != kwargs[old]:
                    raise ValueError(f"{old} is the old name of {new}: give {new} alone")
                kwargs[new] = kwargs.pop(old)
            given = {k: kwargs.pop(k) for k in getattr(cls, "derived", ()) if k in kwargs}
            try:
                init(self, *args, **kwargs)
            except ValueError as err:  # said in the caller's words
                text = str(err)
                for old in used:
                    if text.startswith(f"{old_to_new[old]} "):
                        raise ValueError(old + text[len(old_to_new[old]) :]) from None
                raise
            for k, v in given.items():
                if getattr(self, k) != v:
                    raise ValueError(f"{k} {v} disagrees with the other fields, which make it {getattr(self, k)}")

        __init__.__doc__ = init.__doc__
        cls.__init__ = __init__
        cls.renamed = {**getattr(cls, "renamed", {}), **old_to_new}
        for old, new in old_to_new.items():
            setattr(cls, old, property(lambda self, new=new: getattr(self, new), doc=f"deprecated: {new}"))
        return cls

    return wrap


def add_dataclass_options(parser: argparse.ArgumentParser, cls, prefix: str = "", skip=(), defaults=None) -> dict:
    """Add one option per field; defaults are left to the dataclass (argparse default: None). ``defaults``, an
    instance of ``cls``, is what the help shows as defaults when a tool starts from other values than the
    class's own. Fields set from others (``init=False``) are no options; a field renamed (``renamed_fields``)
    keeps its old option as a deprecated alias (dest: the old name). A class that composes concerns (its
    ``concerns``: (title, dataclass) pairs) has its options grouped by them in the help, each under the first
    concern with the field; returns the groups by title (a tool adds its own options of a concern there)."""
    concerns, hints = getattr(cls, "concerns", ()), typing.get_type_hints(cls)
    groups = {title: parser.add_argument_group(f"{title} options") for title, _ in concerns}
    owner: dict = {}
    for title, concern in concerns:
        nested = [name for name, kind in hints.items() if kind is concern]  # a nested field: its --name-* options
        for name in nested or [f.name for f in dataclasses.fields(concern)]:
            owner.setdefault(name, groups[title])
    _add_options(parser, cls, prefix, skip, defaults, owner)
    return groups


def _add_options(parser, cls, prefix: str, skip, defaults, owner: dict) -> None:
    hints = typing.get_type_hints(cls)
    docs = field_docs(cls)
    for old, new in getattr(cls, "renamed", {}).items():
        if new not in skip:
            flag, kind = f"--{prefix}{new}".replace("_", "-"), hints[new]
            parser.add_argument(f"--{prefix}{old}".replace("_", "-"), dest=f"{prefix}{old}".replace("-", "__"),
                                action=DeprecatedAlias, new=flag, type=parse_bool if kind is bool else kind,
                                default=None, help=argparse.SUPPRESS)  # fmt: skip
    for f in dataclasses.fields(cls):
        if f.name in skip or not f.init:
            continue
        kind, where = hints[f.name], owner.get(f.name, parser)
        if dataclasses.is_dataclass(kind):
            sub = None if defaults is None else getattr(defaults, f.name)
            _add_options(where, kind, f"{prefix}{f.name}-", (), sub, {})
            continue
        if defaults is not None:
            default = getattr(defaults, f.name)
        elif f.default is not dataclasses.MISSING or f.default_factory is not dataclasses.MISSING:
            default = f.default if f.default is not dataclasses.MISSING else f.default_factory()
        else:
            default = dataclasses.MISSING  # a required field: no default to show
        flag, dest = f"--{prefix}{f.name}".replace("_", "-"), f"{prefix}{f.name}".replace("-", "__")
        text = docs.get(f.name, "")
        if default is not dataclasses.MISSING and default is not None and "(default:" not in text:
            text = f"{text} (default: {default})"  # a None default is said in the help's words, if at all
        kind, nargs = option_kind(kind)
        if kind is bool and nargs is None:
            where.add_argument(flag, dest=dest, action=BoolAction, default=None, help=text)
        else:
            metavar = f.metadata.get("metavar", kind.__name__.upper())
            where.add_argument(flag, dest=dest, type=parse_bool if kind is bool else kind, nargs=nargs, default=None,
                               metavar=metavar, help=text)  # fmt: skip


def option_kind(hint) -> tuple[type, str | None]:
    """What one command-line value of a field of type ``hint`` is, and argparse's ``nargs``: ``X | None`` is X
    (None: not given), ``list[X]`` and ``tuple[X, ...]`` take one or more values (``nargs="+"``)."""
    hint = _unoptional(hint)
    origin, args = typing.get_origin(hint), typing.get_args(hint)
    if origin is list and len(args) == 1:
        return args[0], "+"
    if origin is tuple and len(args) == 2 and args[1] is Ellipsis:
        return args[0], "+"
    if not isinstance(hint, type):
        raise TypeError(f"no command-line option for a field of type {hint}")
    return hint, None


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
            out[f.name] = tuple(value) if typing.get_origin(_unoptional(kind)) is tuple else value  # nargs gives a list
    for old, new in getattr(cls, "renamed", {}).items():
        value = getattr(args, f"{prefix}{old}", None)
        if value is not None:
            if out.get(new, value) != value:
                raise ValueError(f"--{old.replace('_', '-')} is the old name of --{new.replace('_', '-')}: "
                                 "give the new one alone")  # fmt: skip
            out[new] = value
    return out


def _unoptional(hint):
    """``X | None`` -> X (a field that may be unset); any other type as it is."""
    args = [a for a in typing.get_args(hint) if a is not type(None)]
    if typing.get_origin(hint) in (typing.Union, types.UnionType) and len(args) == 1:
        return args[0]
    return hint


def replace_nested(obj, overrides: dict):
    """dataclasses.replace that also descends into nested dataclass fields."""
    changes = {}
    for key, value in overrides.items():
        current = getattr(obj, key)
        changes[key] = replace_nested(current, value) if dataclasses.is_dataclass(current) else value
    return dataclasses.replace(obj, **changes)


def check_field_types(obj, cls=None) -> None:
    """Raise ``TypeError`` naming the field when a value does not have its field's type (bool, int, float or
    str; an int is a float, a bool is neither an int nor a float), or a float is NaN: a hand-edited JSON
    config ("learning_rate": "3e-4") fails here, before anything runs, not deep inside training. ``cls``: check
    only its fields (a concern of a config that composes several checks its own)."""
    hints = typing.get_type_hints(cls or type(obj))
    for f in dataclasses.fields(cls or obj):
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
