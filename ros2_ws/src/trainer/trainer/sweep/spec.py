"""A sweep's spec: which training runs it makes, each a set of ``TrainConfig`` overrides, and how each is evaluated.

A spec file (YAML or JSON) holds up to four keys::

    set:     {total_timesteps: 500000}              # overrides every trial shares
    grid:    {clip_mode: [fixed, compensated], seed: [1, 2, 3]}   # their product
    trials:  [{gamma: 0.98}, {gamma: 0.999, eval: {lengths: [2]}}]   # a list, crossed with the grid
    eval:    {stride: 24, episodes: 10}             # morph-eval's options (EvalConfig) for every trial

The command line adds ``--set KEY=VALUE``, ``--grid KEY=V1,V2,...`` and ``--eval KEY=VALUE`` to the file's (or
makes a spec alone). Keys are ``TrainConfig``'s field names, with dashes or underscores (``total-timesteps``),
nested ones as ``policy.FIELD`` or ``policy-FIELD``. Overrides go to ``TrainConfig.from_dict`` as written, so
the trust-region setting is named as the config accepts it. Every trial's config is built here, up front: a
bad key or value is one ``SpecError`` line naming it, before anything runs.

Each trial's name is made of the overrides that vary between trials (``clip_mode=fixed,seed=1``); it names
the trial's run directory inside the sweep's. Evaluation defaults to the late checkpoints (``from_step``:
half the run's steps), what the ranking table reads.
"""

from __future__ import annotations

import dataclasses
import itertools
import json
import typing
from dataclasses import dataclass, field
from pathlib import Path

from morph_core.algo.train import TrainConfig
from morph_core.util.config_cli import check_field_types, parse_bool
from trainer.reports.evaluation import EvalConfig, eval_bodies

SPEC_KEYS = ("set", "grid", "trials", "eval")


class SpecError(ValueError):
    """A spec that cannot make its trials: one line saying what and where."""


@dataclass(frozen=True)
class Trial:
    """One run of the sweep: its name (its run directory's), its TrainConfig overrides and its EvalConfig."""

    name: str
    overrides: dict
    eval: dict = field(default_factory=dict)

    def train_config(self) -> TrainConfig:
        return TrainConfig.from_dict(_nested(self.overrides))

    def eval_config(self, total_timesteps: int) -> EvalConfig:
        values = {"from_step": total_timesteps // 2, **self.eval}  # the late checkpoints, unless told
        return dataclasses.replace(EvalConfig(), **values)

    def to_dict(self) -> dict:
        return {"name": self.name, "overrides": self.overrides, "eval": self.eval}

    @classmethod
    def from_dict(cls, d: dict) -> Trial:
        return cls(d["name"], d["overrides"], d.get("eval", {}))


@dataclass
class SweepSpec:
    set: dict = field(default_factory=dict)
    grid: dict = field(default_factory=dict)
    trials: list = field(default_factory=list)
    eval: dict = field(default_factory=dict)

    def expand(self) -> list[Trial]:
        """The trials, each validated (its TrainConfig and EvalConfig built): ``SpecError`` otherwise."""
        shared = {_train_key(k): v for k, v in self.set.items()}
        grid = {_train_key(k): _as_list(k, v) for k, v in self.grid.items()}
        entries = []
        for i, entry in enumerate(self.trials or [{}]):
            if not isinstance(entry, dict):
                raise SpecError(f"trials[{i}] must be a mapping of overrides, got {_short(entry)}")
            own_eval = entry.get("eval", {})
            if not isinstance(own_eval, dict):
                raise SpecError(f"trials[{i}].eval must be a mapping of morph-eval options, got {_short(own_eval)}")
            entries.append(({_train_key(k): v for k, v in entry.items() if k != "eval"}, own_eval))
        varying = [*dict.fromkeys(k for own, _ in entries for k in own if len(entries) > 1), *grid]
        trials, names = [], {}
        for own, own_eval in entries:
            for combo in itertools.product(*grid.values()):
                overrides = {**shared, **own, **dict(zip(grid, combo, strict=True))}
                overrides = {k: _coerce(k, v) for k, v in overrides.items()}
                name = ",".join(f"{k}={_text(overrides[k])}" for k in varying if k in overrides) or "trial"
                if name in names:
                    raise SpecError(f"two trials have the same overrides: {name}")
                names[name] = True
                trial = Trial(name, overrides, _eval_values({**self.eval, **own_eval}))
                try:
                    cfg = trial.train_config()
                except (TypeError, ValueError) as err:
                    raise SpecError(f"trial {name}: {_one_line(err)}") from None
                _check_eval(trial, cfg.total_timesteps)
                trials.append(trial)
        return trials


def load_spec(path: Path | None, sets=(), grids=(), evals=()) -> SweepSpec:
    """The spec of ``path`` (YAML or JSON; None: an empty one) with the command line's ``KEY=VALUE`` texts
    added (``grids``: ``KEY=V1,V2``); a later value of a key replaces an earlier one."""
    raw: object = {}
    if path is not None:
        try:
            text = Path(path).read_text()
        except (OSError, UnicodeDecodeError) as err:
            raise SpecError(f"{path}: cannot read it ({_one_line(err)})") from None
        raw = _parse_text(path, text)
    if raw is None:
        raw = {}
    if not isinstance(raw, dict):
        raise SpecError(f"{path}: a spec is a mapping with keys {', '.join(SPEC_KEYS)}, got {_short(raw)}")
    unknown = [str(k) for k in raw if k not in SPEC_KEYS]
    if unknown:
        raise SpecError(f"{path}: unknown key(s) {', '.join(unknown)}; a spec has {', '.join(SPEC_KEYS)}")
    parts = {}
    for key in SPEC_KEYS:
        value = raw.get(key)
        want = list if key == "trials" else dict
        if value is None:
            value = want()
        if not isinstance(value, want):
            raise SpecError(f"{path}: {key} must be a {'list' if want is list else 'mapping'}, got {_short(value)}")
        parts[key] = value
    for k in list(parts["set"]) + list(parts["grid"]) + list(parts["eval"]):
        if not isinstance(k, str):
            raise SpecError(f"{path}: option names are text, got {_short(k)}")
    for text in sets:
        k, v = _key_value("--set", text)
        parts["set"][k] = v
    for text in grids:
        k, v = _key_value("--grid", text)
        parts["grid"][k] = [x.strip() for x in v.split(",")]
    for text in evals:
        k, v = _key_value("--eval", text)
        parts["eval"][k] = v
    return SweepSpec(**parts)


def _parse_text(path, text: str):
    if str(path).endswith(".json"):
        try:
            return json.loads(text)
        except ValueError as err:
            raise SpecError(f"{path}: not JSON ({_one_line(err)})") from None
    import yaml  # Ray Tune's own dependency, so it is there wherever morph-sweep runs

    try:
        return yaml.safe_load(text)
    except yaml.YAMLError as err:
        raise SpecError(f"{path}: not YAML ({_one_line(err)})") from None
    except RecursionError:
        raise SpecError(f"{path}: nested too deeply") from None


def _key_value(option: str, text: str) -> tuple[str, str]:
    key, sep, value = text.partition("=")
    if not sep or not key.strip():
        raise SpecError(f"{option} {text!r}: expected KEY=VALUE")
    return key.strip(), value.strip()


def _train_fields() -> dict[str, type]:
    return typing.get_type_hints(TrainConfig)


def _train_key(key) -> str:
    """A key as ``TrainConfig`` spells it: underscores, nested fields dotted (``policy.hidden``); a key the
    config does not know is passed on as written, for ``TrainConfig.from_dict`` to accept (an alias) or refuse."""
    if not isinstance(key, str) or not key.strip():
        raise SpecError(f"option names are text, got {_short(key)}")
    name = key.strip().replace("-", "_")
    hints = _train_fields()
    if name in hints or "." in name:
        return name
    for parent, kind in hints.items():  # policy_hidden (from --policy-hidden) -> policy.hidden
        if dataclasses.is_dataclass(kind) and name.startswith(parent + "_"):
            return f"{parent}.{name[len(parent) + 1 :]}"
    return name


def _field_type(key: str):
    hints = _train_fields()
    if "." in key:
        parent, _, child = key.partition(".")
        kind = hints.get(parent)
        return typing.get_type_hints(kind).get(child) if dataclasses.is_dataclass(kind) else None
    return hints.get(key)


def _coerce(key: str, value):
    """A command-line text (or a YAML string such as '1e-3') as the field's type; other values as they are,
    for the config's own type checks."""
    kind = _field_type(key)
    if not isinstance(value, str) or kind not in (bool, int, float):
        return value
    try:
        return parse_bool(value) if kind is bool else kind(value)
    except ValueError:
        raise SpecError(f"{key}: expected {kind.__name__}, got {value!r}") from None


def _as_list(key, values) -> list:
    if not isinstance(values, list) or not values:
        raise SpecError(f"grid {key}: a non-empty list of values, got {_short(values)}")
    return values


def _nested(overrides: dict) -> dict:
    """``{"policy.hidden": 64}`` -> ``{"policy": {"hidden": 64}}``."""
    out: dict = {}
    for key, value in overrides.items():
        parent, dot, child = key.partition(".")
        if dot:
            sub = out.setdefault(parent, {})
            if not isinstance(sub, dict):
                raise SpecError(f"{key}: {parent} is given both whole and by field")
            sub[child] = value
        else:
            out[key] = value
    return out


def _eval_values(values: dict) -> dict:
    """EvalConfig's fields (dashes allowed), command-line texts as their types; ``SpecError`` otherwise."""
    hints = typing.get_type_hints(EvalConfig)
    out = {}
    for key, value in values.items():
        if not isinstance(key, str):
            raise SpecError(f"eval: option names are text, got {_short(key)}")
        name = key.strip().replace("-", "_")
        if name not in hints:
            raise SpecError(f"eval: unknown option {key!r}; morph-eval's are {', '.join(hints)}")
        if name == "lengths":
            if isinstance(value, str):  # the command line's --eval lengths=2,3,10
                value = [v.strip() for v in value.split(",") if v.strip()]
            if not isinstance(value, list):
                raise SpecError(f"eval lengths: a list of chain lengths, got {_short(value)}")
            try:
                value = [int(v) if isinstance(v, str) else v for v in value]
            except ValueError:
                raise SpecError(f"eval lengths: chain lengths are integers, got {_short(value)}") from None
        elif isinstance(value, str) and hints[name] is int:
            try:
                value = int(value)
            except ValueError:
                raise SpecError(f"eval {name}: expected int, got {value!r}") from None
        out[name] = value
    return out


def _check_eval(trial: Trial, total_timesteps: int) -> None:
    cfg = trial.eval_config(total_timesteps)
    try:
        check_field_types(cfg)
        if any(isinstance(n, bool) or not isinstance(n, int) for n in cfg.lengths):
            raise TypeError(f"lengths must be integers, got {_short(cfg.lengths)}")
        if any(not 1 <= n <= 64 for n in cfg.lengths):
            raise ValueError(f"lengths must be in 1..64, got {_short(cfg.lengths)}")
        if min(cfg.episodes, cfg.stride, cfg.processes, cfg.env_threads) < 1 or cfg.from_step < 0:
            raise ValueError("episodes, stride, processes and env_threads must be >= 1, from_step >= 0")
        if not eval_bodies(cfg):
            raise ValueError("nothing to evaluate: give lengths or bodies")
    except (TypeError, ValueError) as err:
        raise SpecError(f"trial {trial.name}: eval: {_one_line(err)}") from None


def _text(value) -> str:
    """A value as it reads in a trial's name and directory: no path separator, no spaces."""
    text = json.dumps(value, separators=(",", ":")) if isinstance(value, (dict, list)) else str(value)
    if isinstance(value, bool):
        text = text.lower()
    return text.replace("/", "_").replace(" ", "")


def _short(value) -> str:
    text = repr(value)
    return text if len(text) <= 80 else text[:77] + "..."


def _one_line(err: BaseException) -> str:
    return " ".join(str(err).split()) or type(err).__name__
