"""config_cli's list-valued and optional fields: ``list[X]`` / ``tuple[X, ...]`` take one or more values, ``X |
None`` is unset unless given, and a bad value is refused in one line (exit code 2), never taken."""

from __future__ import annotations

import contextlib
import io
import random
from dataclasses import dataclass, field
from pathlib import Path

import pytest

from morph_core.util.config_cli import (
    CommandLineParser,
    add_dataclass_options,
    option_kind,
    overrides_from_args,
)


@dataclass(frozen=True)
class Source:
    """A source's config with every kind of field the sources' configs have."""

    names: tuple[str, ...] = field(default=(), metadata={"metavar": "NS"})
    """names, one or more"""
    counts: list[int] | None = None
    """counts, one or more"""
    where: Path | None = None
    """a path"""
    limit: int | None = None
    """a limit (default: none)"""
    rate: float = 1.0
    """a rate"""
    flag: bool = False
    """a flag"""


def _parser() -> CommandLineParser:
    parser = CommandLineParser(prog="tool")
    add_dataclass_options(parser, Source)
    return parser


def _parse(argv: list[str]) -> tuple[Source | None, str]:
    """The config the arguments give, or None and what the tool said on stderr."""
    err = io.StringIO()
    with contextlib.redirect_stderr(err):
        try:
            args = _parser().parse_args(argv)
        except SystemExit as exit_:
            assert exit_.code == 2
            return None, err.getvalue()
    return Source(**overrides_from_args(args, Source)), err.getvalue()


def test_list_fields_take_several_values_and_optional_ones_stay_unset():
    cfg, _ = _parse(["--names", "a", "b", "--counts", "3", "4", "--where", "x/y", "--flag"])
    assert cfg == Source(names=("a", "b"), counts=[3, 4], where=Path("x/y"), flag=True)
    assert isinstance(cfg.names, tuple)  # the field's own type, not argparse's list
    assert _parse([])[0] == Source()
    help_ = {a.dest: a for a in _parser()._actions}
    assert help_["names"].nargs == "+" and help_["names"].metavar == "NS" and help_["counts"].nargs == "+"
    assert help_["rate"].help == "a rate (default: 1.0)"
    assert help_["limit"].help == "a limit (default: none)"  # said in its words, not twice
    assert help_["where"].help == "a path"  # None: nothing to show


@pytest.mark.parametrize("hint", [dict[str, int], tuple[int, str], int | str])
def test_a_field_type_with_no_option_is_said(hint):
    with pytest.raises(TypeError, match="no command-line option"):
        option_kind(hint)


def test_a_list_option_without_values_or_with_a_bad_one_is_refused_in_one_line():
    for argv, said in (
        (["--names"], "expected at least one argument"),
        (["--counts", "3", "x"], "invalid int value: 'x'"),
        (["--counts", "--names", "a"], "expected at least one argument"),
    ):
        cfg, err = _parse(argv)
        assert cfg is None and said in err, (argv, err)
        assert err.count("\n") == 2 and err.startswith("tool: error: "), err  # the error and the hint


def test_fuzzed_list_arguments_parse_to_their_types_or_are_refused_in_one_line():
    rng = random.Random(54)
    words = ["1", "-2", "0x3", "x", "", " ", "é", "3.5", "nan", "--", "-", "true", "a b", "\x00"]
    options = ["--names", "--counts", "--where", "--limit", "--rate", "--flag"]
    outcomes = {"parsed": 0, "refused": 0}
    for _ in range(600):
        argv = []
        for _ in range(rng.randint(0, 4)):
            argv.append(rng.choice(options))
            argv += [rng.choice(words) for _ in range(rng.randint(0, 3))]
        cfg, err = _parse(argv)
        if cfg is None:
            lines = err.splitlines()
            assert len(lines) == 2 and lines[0].startswith("tool: error: ") and lines[1] == "see tool --help", err
            outcomes["refused"] += 1
            continue
        outcomes["parsed"] += 1
        assert isinstance(cfg.names, tuple) and all(isinstance(n, str) for n in cfg.names)
        assert cfg.counts is None or (cfg.counts and all(type(c) is int for c in cfg.counts))
        assert cfg.where is None or isinstance(cfg.where, Path)
        assert cfg.limit is None or type(cfg.limit) is int
        assert type(cfg.rate) is float and type(cfg.flag) is bool
    assert outcomes["parsed"] > 50 and outcomes["refused"] > 50, outcomes
