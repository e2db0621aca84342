"""Body families: which bodies (swimmers: kinematic trees of hinges; centipedes) an env draws, from one text spec.

A spec is one or more items separated by commas; at each reset one item is drawn uniformly
(no draw when there is one item), then one of its members (no draw when it has one):

    N  |  LO-HI  |  chain:N  |  chain:LO-HI   chains of N (LO..HI) joints, length drawn uniformly
    star:KxA                                   K arms of A joints each off the torso     (K*A joints)
    y:SxB                                      a stem of S joints, then two branches of B (S+2B joints)
    comb:S                                     a spine of S joints; each spine link but the last
                                               carries a one-joint tooth                  (2S-1 joints)
    random:LO-HI[:bB]                          a random tree of LO..HI joints, at most B children per
                                               link (the torso included); B defaults to 2
    centipede:N  |  centipede:LO-HI            a centipede (``env.centipede``) of N (LO..HI) leg pairs,
                                               drawn uniformly                             (4N joints)
    legged:LxJ[:TORSO][:sLO-HI]                generated legged bodies (``env.legged_model``): L legs (4, 6,
                                               8; a range LO-HI takes its even sizes), J joints per leg (2,
                                               3, or 2-3), a torso (round, long, wide; default any), a body
                                               seed in LO..HI (default ``LEGGED_TRAIN_SEEDS``); each drawn
                                               uniformly                                    (L*J joints)
    mjcf:PATH                                  a user's MJCF file (``env.mjcf_body``): a walker when its root
                                               has a free joint, a swimmer when it is planar; refused as the
                                               sim node's ``model_file`` is. PATH holds no comma.

Every size of a named shape (K, A, S, B) may be a range ``LO-HI`` too (``star:2-3x1-2``: the four stars
of 2..3 arms of 1..2 joints, one drawn uniformly). Limits: chains 1..``MAX_JOINTS`` joints (as
``num_joints``), trees (named or random) at most ``MAX_TREE_JOINTS``,
``star`` K in 2..``STAR_MAX_ARMS``, ``y`` S >= 1, B >= 1, ``comb`` S >= 3 (``comb:2`` would be
``y:1x1``), ``random`` B in 1..``RANDOM_MAX_BRANCHING``; the caps come from the stability sweep
(``bench/check_body_stability.py``, docs/bodies.md); centipedes ``MIN_LEG_PAIRS``..``MAX_LEG_PAIRS`` leg pairs.
A bad spec raises ``ValueError`` with the reason.

Centipedes and legged bodies are walkers: Ant-v5's task (``env.centipede.MorphCentipedeEnv``).
Swimmers and walkers may be mixed in one spec (``2-4,centipede:2-3``): each env draws its family at
every reset like any item. The policy's global input is then the centipede's 12 features, a swimmer's 4
(yaw, yaw rate, vx, vy: the centipede's first four, same meanings) zero-padded (``BodyMix.global_features``).
A swimmer draw is a ``KinematicTree``, a centipede draw a ``Centipede`` (its size; ``.tree`` its tree).

A spec of chains alone draws as ``MorphSwimmerEnv(num_joints=(LO, HI))`` always has: one chain item
``LO-HI`` draws ``rng.integers(LO, HI + 1)`` when LO != HI and nothing when LO == HI, so chain runs stay
bit for bit what they were.

Joints are numbered in depth-first pre-order from the torso (a link's children in the order listed
above: a Y's stem, then its first branch, then its second; a comb's tooth before the spine goes on),
which is MuJoCo's qpos order for the MJCF ``env.model`` writes; drawn trees carry the swimmer's
joint names ``motor{k}_rot`` and root link ``torso``. ``body_label`` names a body in logs:
``chain-N``, a named shape's label (``star-3x2``, ``y-1x2``, ``comb-4``), ``centipede-N``, else ``tree-`` and
8 hex digits of its topology hash.
"""

from __future__ import annotations

import dataclasses
import re
from dataclasses import dataclass
from functools import cache

import numpy as np

from morph_core.constants import MAX_JOINTS
from morph_core.env.centipede_model import JOINTS_PER_LEG_PAIR, MAX_LEG_PAIRS, MIN_LEG_PAIRS, centipede_model
from morph_core.env.legged_model import LEGGED_JOINTS_PER_LEG, LEGGED_LEGS, MAX_SEED, TORSOS, LeggedBody
from morph_core.env.mjcf_body import MjcfBody
from morph_core.policy.config import PolicyConfig
from morph_core.policy.index_plan import joint_depths
from morph_core.policy.tree import KinematicTree, swimmer_joint_names

MAX_TREE_JOINTS = 32
"""most joints of a tree family's member: chains of 56+ joints diverge at Swimmer-v5's timestep from the reset
noise alone (docs/bodies.md); trees are kept well clear of that depth, and the sweep covers every size allowed"""
STAR_MAX_ARMS = 4
"""most arms off the torso: the rest directions fan over 120 degrees (``env.model``); more would crowd it"""
RANDOM_MAX_BRANCHING = 3
"""largest ``:bB`` of a random family"""
DEFAULT_BRANCHING = 2
MAX_SPEC_CHARS = 1000
MAX_ITEMS = 64

_INT = r"(\d{1,4})"
_RANGE = rf"{_INT}(?:-{_INT})?"
_CHAIN_RE = re.compile(rf"(?:chain:)?{_RANGE}")
_STAR_RE = re.compile(rf"star:{_RANGE}x{_RANGE}")
_Y_RE = re.compile(rf"y:{_RANGE}x{_RANGE}")
_COMB_RE = re.compile(rf"comb:{_RANGE}")
_RANDOM_RE = re.compile(rf"random:{_RANGE}(?::b{_INT})?")
_CENTIPEDE_RE = re.compile(rf"centipede:{_RANGE}")
_LEGGED_RE = re.compile(rf"legged:{_RANGE}x{_RANGE}(?::(round|long|wide))?(?::s(\d{{1,10}})(?:-(\d{{1,10}}))?)?")
LEGGED_TRAIN_SEEDS = (0, 99)
"""body seeds a ``legged:`` item draws without ``:s``; evaluations hold out seeds from 1000 on"""
SWIMMER_GLOBAL_FEATURES = 4
"""a swimmer's global vector: yaw, yaw rate, vx, vy (``swimmer_env.GLOBAL_FEATURES``)"""
CENTIPEDE_GLOBAL_FEATURES = 12
"""a centipede's (``centipede.GLOBAL_FEATURES``), the swimmer's four first"""


def swimmer_tree(parents) -> KinematicTree:
    """The swimmer whose joints have these parents: joint names ``motor{k}_rot``, root link ``torso``."""
    return KinematicTree(swimmer_joint_names(len(parents)), np.asarray(parents, dtype=np.int64), "torso")


def _range_text(lo: int, hi: int) -> str:
    return str(lo) if lo == hi else f"{lo}-{hi}"


def _pair(lo: str, hi: str | None, what: str, least: int, most: int = MAX_JOINTS) -> tuple[int, int]:
    a = int(lo)
    b = a if hi is None else int(hi)
    if a > b:
        raise ValueError(f"{what}: empty range {a}-{b}")
    if a < least:
        raise ValueError(f"{what} must be at least {least}, got {a}")
    if b > most:
        raise ValueError(f"{what} must be at most {most}, got {b}")
    return a, b


# -- parent arrays of the named shapes (pre-order) ---------------------------------------------------------
def star_parents(arms: int, length: int) -> list[int]:
    out: list[int] = []
    for _ in range(arms):
        start = len(out)
        out += [-1] + list(range(start, start + length - 1))
    return out


def y_parents(stem: int, branch: int) -> list[int]:
    out = list(range(-1, stem - 1))
    for _ in range(2):
        start = len(out)
        out += [stem - 1] + list(range(start, start + branch - 1))
    return out


def comb_parents(spine: int) -> list[int]:
    out = [-1]
    for _ in range(spine - 1):
        s = len(out) - 1  # the last spine joint
        out += [s, s]  # its tooth, then the next spine joint
    return out


def tree_depth(parents) -> int:
    """Joints on the longest torso-to-tip path (a chain's length)."""
    return int(joint_depths(parents).max()) + 1


# -- families ------------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class _Finite:
    """A family with a finite list of members, drawn uniformly (no draw when there is one)."""

    def shapes(self) -> list[tuple[str, list[int]]]:  # (label, parents)
        raise NotImplementedError

    def members(self) -> list[KinematicTree]:
        return [swimmer_tree(p) for _, p in self.shapes()]

    @property
    def joint_range(self) -> tuple[int, int]:
        sizes = [len(p) for _, p in self.shapes()]
        return min(sizes), max(sizes)

    def draw(self, rng: np.random.Generator) -> KinematicTree:
        shapes = self.shapes()
        k = 0 if len(shapes) == 1 else int(rng.integers(len(shapes)))
        return swimmer_tree(shapes[k][1])

    def first(self) -> KinematicTree:
        return swimmer_tree(self.shapes()[0][1])


@dataclass(frozen=True)
class ChainFamily(_Finite):
    lo: int
    hi: int

    def __str__(self) -> str:
        return _range_text(self.lo, self.hi)

    def shapes(self):
        return [(chain_label(n), list(range(-1, n - 1))) for n in range(self.lo, self.hi + 1)]

    @property
    def joint_range(self) -> tuple[int, int]:
        return self.lo, self.hi

    def draw(self, rng: np.random.Generator) -> KinematicTree:
        # Exactly MorphSwimmerEnv's chain draw: nothing when lo == hi.
        n = self.lo if self.lo == self.hi else int(rng.integers(self.lo, self.hi + 1))
        return KinematicTree.chain(n)


@dataclass(frozen=True)
class StarFamily(_Finite):
    arms: tuple[int, int]
    length: tuple[int, int]

    def __str__(self) -> str:
        return f"star:{_range_text(*self.arms)}x{_range_text(*self.length)}"

    def shapes(self):
        return [
            (f"star-{k}x{a}", star_parents(k, a))
            for k in range(self.arms[0], self.arms[1] + 1)
            for a in range(self.length[0], self.length[1] + 1)
        ]


@dataclass(frozen=True)
class YFamily(_Finite):
    stem: tuple[int, int]
    branch: tuple[int, int]

    def __str__(self) -> str:
        return f"y:{_range_text(*self.stem)}x{_range_text(*self.branch)}"

    def shapes(self):
        return [
            (f"y-{s}x{b}", y_parents(s, b))
            for s in range(self.stem[0], self.stem[1] + 1)
            for b in range(self.branch[0], self.branch[1] + 1)
        ]


@dataclass(frozen=True)
class CombFamily(_Finite):
    spine: tuple[int, int]

    def __str__(self) -> str:
        return f"comb:{_range_text(*self.spine)}"

    def shapes(self):
        return [(f"comb-{s}", comb_parents(s)) for s in range(self.spine[0], self.spine[1] + 1)]


@dataclass(frozen=True)
class RandomTreeFamily:
    """Trees of lo..hi joints (count drawn uniformly, as a chain's length), built joint by joint in
    pre-order: each new joint hangs off a link drawn uniformly from those on the path from the torso to
    the last joint's child link that have fewer than ``branching`` children (the only links a pre-order
    may still extend)."""

    lo: int
    hi: int
    branching: int

    def __str__(self) -> str:
        return f"random:{_range_text(self.lo, self.hi)}:b{self.branching}"

    @property
    def joint_range(self) -> tuple[int, int]:
        return self.lo, self.hi

    def members(self) -> None:
        return None

    def draw(self, rng: np.random.Generator) -> KinematicTree:
        n = self.lo if self.lo == self.hi else int(rng.integers(self.lo, self.hi + 1))
        children = [0] * (n + 1)  # per link; link 0 is the torso, link j + 1 joint j's child
        path = [0]
        parents: list[int] = []
        for j in range(n):
            open_links = [link for link in path if children[link] < self.branching]
            link = open_links[0] if len(open_links) == 1 else open_links[int(rng.integers(len(open_links)))]
            parents.append(link - 1)
            children[link] += 1
            path = path[: path.index(link) + 1] + [j + 1]
        return swimmer_tree(parents)

    def first(self) -> KinematicTree:
        return KinematicTree.chain(self.lo)


@dataclass(frozen=True)
class Centipede:
    """A centipede body of ``leg_pairs`` leg pairs (``env.centipede.MorphCentipedeEnv``): what a centipede
    family draws where a swimmer family draws a ``KinematicTree``."""

    leg_pairs: int

    @property
    def num_joints(self) -> int:
        return JOINTS_PER_LEG_PAIR * self.leg_pairs

    @property
    def label(self) -> str:
        return f"centipede-{self.leg_pairs}"

    @property
    def tree(self) -> KinematicTree:
        """Its kinematic tree, read off the compiled model (MJCF joint names, root link ``torso_0``)."""
        return centipede_tree(self.leg_pairs)


@cache
def centipede_tree(leg_pairs: int) -> KinematicTree:
    return KinematicTree.from_mujoco(centipede_model(leg_pairs))


@dataclass(frozen=True)
class CentipedeFamily:
    """Centipedes of lo..hi leg pairs, the size drawn uniformly (``MorphCentipedeEnv(leg_pairs=(lo, hi))``'s
    draw: nothing when lo == hi)."""

    lo: int
    hi: int

    def __str__(self) -> str:
        return f"centipede:{_range_text(self.lo, self.hi)}"

    @property
    def joint_range(self) -> tuple[int, int]:
        return JOINTS_PER_LEG_PAIR * self.lo, JOINTS_PER_LEG_PAIR * self.hi

    def members(self) -> list[Centipede]:
        return [Centipede(n) for n in range(self.lo, self.hi + 1)]

    def draw(self, rng: np.random.Generator) -> Centipede:
        return Centipede(self.lo if self.lo == self.hi else int(rng.integers(self.lo, self.hi + 1)))

    def first(self) -> Centipede:
        return Centipede(self.lo)


@dataclass(frozen=True)
class LeggedFamily:
    """Generated legged bodies (``env.legged_model.LeggedBody``): legs, joints per leg, torso and seed, each
    drawn uniformly in that order (a fixed one not drawn)."""

    legs: tuple[int, ...]
    joints: tuple[int, ...]
    torsos: tuple[str, ...]
    seeds: tuple[int, int]

    def __str__(self) -> str:
        legs = _range_text(self.legs[0], self.legs[-1])
        joints = _range_text(self.joints[0], self.joints[-1])
        torso = "" if self.torsos == TORSOS else f":{self.torsos[0]}"
        return f"legged:{legs}x{joints}{torso}:s{_range_text(*self.seeds)}"

    @property
    def joint_range(self) -> tuple[int, int]:
        return self.legs[0] * self.joints[0], self.legs[-1] * self.joints[-1]

    def _count(self) -> int:
        return len(self.legs) * len(self.joints) * len(self.torsos) * (self.seeds[1] - self.seeds[0] + 1)

    def members(self) -> list[LeggedBody] | None:
        """Every body, when there are at most 64; None otherwise (as a random family)."""
        if self._count() > 64:
            return None
        return [LeggedBody(n, j, t, s) for n in self.legs for j in self.joints for t in self.torsos
                for s in range(self.seeds[0], self.seeds[1] + 1)]  # fmt: skip

    def draw(self, rng: np.random.Generator) -> LeggedBody:
        def pick(options):
            return options[0] if len(options) == 1 else options[int(rng.integers(len(options)))]

        lo, hi = self.seeds
        legs, joints, torso = pick(self.legs), pick(self.joints), pick(self.torsos)
        return LeggedBody(legs, joints, torso, lo if lo == hi else int(rng.integers(lo, hi + 1)))

    def first(self) -> LeggedBody:
        return LeggedBody(self.legs[0], self.joints[0], self.torsos[0], self.seeds[0])


def _legged_family(m: re.Match) -> LeggedFamily:
    lo, hi = _pair(m[1], m[2], "legged legs", LEGGED_LEGS[0], LEGGED_LEGS[-1])
    legs = tuple(n for n in LEGGED_LEGS if lo <= n <= hi)
    if not legs:
        raise ValueError(f"legged legs must be one of {LEGGED_LEGS}, got {_range_text(lo, hi)}")
    jlo, jhi = _pair(m[3], m[4], "legged joints per leg", LEGGED_JOINTS_PER_LEG[0], LEGGED_JOINTS_PER_LEG[-1])
    torsos = TORSOS if m[5] is None else (m[5],)
    seeds = LEGGED_TRAIN_SEEDS if m[6] is None else _pair(m[6], m[7], "legged body seed", 0, MAX_SEED)
    return LeggedFamily(legs, tuple(range(jlo, jhi + 1)), torsos, seeds)


@dataclass(frozen=True)
class MjcfFamily:
    """One user's MJCF (``env.mjcf_body.MjcfBody``); the file is read when first needed (``RobotModelError``,
    a ValueError, says why it is refused)."""

    body: MjcfBody

    def __str__(self) -> str:
        return f"mjcf:{self.body.path}"

    @property
    def joint_range(self) -> tuple[int, int]:
        return self.body.num_joints, self.body.num_joints

    @property
    def is_walker(self) -> bool:
        return self.body.task == "walker"

    def members(self) -> list[MjcfBody]:
        return [self.body]

    def draw(self, rng: np.random.Generator) -> MjcfBody:
        return self.body

    def first(self) -> MjcfBody:
        return self.body


Family = (
    ChainFamily | StarFamily | YFamily | CombFamily | RandomTreeFamily | CentipedeFamily | LeggedFamily | MjcfFamily
)
WALKER_FAMILIES = (CentipedeFamily, LeggedFamily)
"""families run by Ant-v5's task (``MorphCentipedeEnv``) rather than the swimmer's (and an ``MjcfFamily`` whose
root is free)"""
Body = KinematicTree | Centipede | LeggedBody | MjcfBody
"""what a ``BodyMix`` draws"""


def _parse_item(item: str) -> Family:
    if not item:
        raise ValueError("empty item (two commas in a row, or a comma at an end)")
    if m := _CHAIN_RE.fullmatch(item):
        return ChainFamily(*_pair(m[1], m[2], "chain length", 1))
    if m := _STAR_RE.fullmatch(item):
        family = StarFamily(_pair(m[1], m[2], "star arms", 2, STAR_MAX_ARMS), _pair(m[3], m[4], "star arm joints", 1))
    elif m := _Y_RE.fullmatch(item):
        family = YFamily(_pair(m[1], m[2], "y stem joints", 1), _pair(m[3], m[4], "y branch joints", 1))
    elif m := _COMB_RE.fullmatch(item):
        family = CombFamily(_pair(m[1], m[2], "comb spine joints", 3))
    elif m := _CENTIPEDE_RE.fullmatch(item):
        return CentipedeFamily(*_pair(m[1], m[2], "centipede leg pairs", MIN_LEG_PAIRS, MAX_LEG_PAIRS))
    elif m := _LEGGED_RE.fullmatch(item):
        return _legged_family(m)
    elif item.startswith("mjcf:"):
        if not item[5:].strip():
            raise ValueError("mjcf: needs a path to an MJCF file")
        return MjcfFamily(MjcfBody(item[5:].strip()))
    elif m := _RANDOM_RE.fullmatch(item):
        lo, hi = _pair(m[1], m[2], "random tree joints", 1, MAX_TREE_JOINTS)
        b = DEFAULT_BRANCHING if m[3] is None else int(m[3])
        if not 1 <= b <= RANDOM_MAX_BRANCHING:
            raise ValueError(f"random tree branching must be in 1..{RANDOM_MAX_BRANCHING}, got b{b}")
        return RandomTreeFamily(lo, hi, b)
    else:
        family_name = item.split(":", 1)[0]
        known = (
            "N, LO-HI, chain:, star:KxA, y:SxB, comb:S, random:LO-HI[:bB], centipede:LO-HI, "
            "legged:LxJ[:TORSO][:sLO-HI], mjcf:PATH"
        )
        families = ("chain", "star", "y", "comb", "random", "centipede", "legged", "mjcf")
        if ":" in item and family_name not in families:
            raise ValueError(f"unknown body family {family_name[:20]!r} (known: {known})")
        raise ValueError(f"cannot read body item {item[:40]!r} (forms: {known})")
    lo, hi = family.joint_range
    if hi > MAX_TREE_JOINTS:
        raise ValueError(f"{family} has a member of {hi} joints, more than a tree's maximum of {MAX_TREE_JOINTS}")
    return family


@dataclass(frozen=True)
class BodyMix:
    """The families of a spec; ``draw`` picks one uniformly, then one of its members."""

    items: tuple[Family, ...]

    def __str__(self) -> str:
        return ",".join(map(str, self.items))

    def draw(self, rng: np.random.Generator) -> Body:
        item = self.items[0] if len(self.items) == 1 else self.items[int(rng.integers(len(self.items)))]
        return item.draw(rng)

    def first(self) -> Body:
        """A member drawn without randomness (the first item's first or smallest): the body an env has
        before its first reset."""
        return self.items[0].first()

    @property
    def joint_range(self) -> tuple[int, int]:
        ranges = [item.joint_range for item in self.items]
        return min(r[0] for r in ranges), max(r[1] for r in ranges)

    @property
    def max_joints(self) -> int:
        return self.joint_range[1]

    @property
    def chains_only(self) -> bool:
        return all(isinstance(item, ChainFamily) for item in self.items)

    @property
    def has_centipedes(self) -> bool:
        return any(isinstance(item, CentipedeFamily) for item in self.items)

    @property
    def has_walkers(self) -> bool:
        """Whether any family is run by Ant-v5's task: centipedes, legged bodies."""
        return any(
            isinstance(item, WALKER_FAMILIES) or (isinstance(item, MjcfFamily) and item.is_walker)
            for item in self.items
        )

    @property
    def swimmers_only(self) -> bool:
        return not self.has_walkers

    @property
    def global_features(self) -> int:
        """The policy's global input width for these bodies: a swimmer's 4, or 12 with any walker (a
        swimmer's four then zero-padded)."""
        return CENTIPEDE_GLOBAL_FEATURES if self.has_walkers else SWIMMER_GLOBAL_FEATURES

    def members(self) -> list[Body] | None:
        """Every body the mix can draw, in spec order without repeats; None when a family is random."""
        out: list[Body] = []
        seen: set[Body] = set()
        for item in self.items:
            trees = item.members()
            if trees is None:
                return None
            for tree in trees:
                if tree not in seen:
                    seen.add(tree)
                    out.append(tree)
        return out


def parse_bodies(spec: str) -> BodyMix:
    """The ``BodyMix`` of a spec (grammar in the module docstring); ValueError says why a spec is bad."""
    if not isinstance(spec, str):
        raise ValueError(f"a body spec is a string, got {type(spec).__name__}")
    if len(spec) > MAX_SPEC_CHARS:
        raise ValueError(f"body spec longer than {MAX_SPEC_CHARS} characters")
    text = spec.strip()
    if not text:
        raise ValueError("empty body spec")
    items = [part.strip() for part in text.split(",")]
    if len(items) > MAX_ITEMS:
        raise ValueError(f"more than {MAX_ITEMS} items in a body spec")
    return BodyMix(tuple(_parse_item(item) for item in items))


@cache
def _named_labels() -> dict[bytes, str]:
    """Parents (int64 bytes) -> label of every shape the named families can draw."""
    families: list[_Finite] = [
        StarFamily((2, STAR_MAX_ARMS), (1, MAX_TREE_JOINTS // 2)),
        YFamily((1, MAX_TREE_JOINTS - 2), (1, (MAX_TREE_JOINTS - 1) // 2)),
        CombFamily((3, (MAX_TREE_JOINTS + 1) // 2)),
    ]
    labels: dict[bytes, str] = {}
    for family in families:
        for label, parents in family.shapes():
            if len(parents) <= MAX_TREE_JOINTS:
                key = np.asarray(parents, dtype=np.int64).tobytes()
                if key in labels:  # two named shapes with one parent array: the families would be ambiguous
                    raise AssertionError(f"{label} is also {labels[key]}")
                labels[key] = label
    return labels


def chain_label(num_joints: int) -> str:
    """The label of the chain of ``num_joints`` joints: ``chain-N``."""
    return f"chain-{num_joints}"


def is_chain_label(label: str) -> bool:
    """Whether ``label`` (a ``body_label``) names a chain."""
    return label.startswith("chain-")


def body_label(body: int | Body) -> str:
    """``chain-N`` for a chain (or a chain length), the named shape's label (``star-3x2``, ``y-1x2``,
    ``comb-4``) for a tree of a named family (recognised by its parent array, which is what the topology
    hash covers), ``centipede-N`` for a centipede, else ``tree-`` and the first 8 hex digits of
    ``tree.topology_hash``."""
    if isinstance(body, int):
        return chain_label(body)
    if isinstance(body, Centipede | LeggedBody | MjcfBody):
        return body.label
    tree = body
    if tree.is_chain:
        return chain_label(tree.num_joints)
    label = _named_labels().get(tree.parents.astype(np.int64).tobytes())
    return label if label is not None else "tree-" + tree.topology_hash[:8]


def is_walker(body) -> bool:
    """Whether ``body`` (what a ``BodyMix`` draws, or a chain length) runs Ant-v5's task: a centipede, a
    legged body, a user's MJCF with a free root."""
    return isinstance(body, Centipede | LeggedBody) or (isinstance(body, MjcfBody) and body.task == "walker")


def swimmers_only(mix: BodyMix, what: str) -> BodyMix:
    """``mix`` when it holds swimmers alone, else ValueError naming ``what`` refuses walkers."""
    if mix.has_walkers:
        raise ValueError(f"{what} runs swimmers; {str(mix)!r} holds walkers (MorphCentipedeEnv runs those)")
    return mix


def fit_global_features(policy: PolicyConfig, mix: BodyMix) -> PolicyConfig:
    """``policy`` reading ``mix``'s global width: a policy left at the swimmer's default 4 gets the mix's (12 with
    centipedes); another width that disagrees is refused (ValueError), since the env writes the mix's."""
    width = mix.global_features
    if policy.global_features == width:
        return policy
    if policy.global_features == SWIMMER_GLOBAL_FEATURES:
        return dataclasses.replace(policy, global_features=width)
    raise ValueError(
        f"bodies {str(mix)!r} give {width} global features, the policy reads {policy.global_features}: "
        f"leave policy global_features unset (or {width})"
    )
