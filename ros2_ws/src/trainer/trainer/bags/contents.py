"""What recorded bags hold for learning: a bag's summary (topics, episodes, steps per body, skips by reason),
its task and robot, and its transitions as arrays. ``morph-bag`` (``bags.cli``) prints them; ``morph-train
--from-bags`` and the rounds train on them.

A bag is read by ``trainer.bags.io``; records become transitions as ``morph_core.protocol.transitions``
describes. The robot is the bag's ``robot_description`` (its tree, the joints bound by name); a bag without
one holds chains, each state's joints in the message's order.
"""

from __future__ import annotations

import dataclasses
import re
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path

from morph_core.env.bodies import body_label
from morph_core.msgs.records import DescriptionRecord, OdometryRecord
from morph_core.protocol.joint_map import JointMap
from morph_core.protocol.transition_batch import TransitionBatch
from morph_core.protocol.transitions import (
    SkipCounts,
    StreamStats,
    TransitionAssembler,
    TransitionConfig,
)
from trainer.bags.io import BagReader, first_description
from trainer.codec import DESCRIPTION_TOPIC

NO_DESCRIPTION = "no robot_description: joints taken as chains in message order"


@dataclass
class BagSummary:
    """One bag (or the total over several): what it held and what became of it."""

    path: str
    topics: list[tuple[str, str, int]] = field(default_factory=list)
    """(topic, type, messages) of every topic in the bag"""
    rejected: Counter = field(default_factory=Counter)
    """messages the reader could not decode, by (topic, reason)"""
    warnings: list[str] = field(default_factory=list)
    skips: SkipCounts = field(default_factory=SkipCounts)
    stats: StreamStats = field(default_factory=StreamStats)
    steps_per_chain: Counter = field(default_factory=Counter)
    """transitions per number of joints"""
    descriptions: int = 0
    """robot_description messages read"""
    described: list[str] = field(default_factory=list)
    """the bodies (``env.bodies.body_label``) the descriptions that read as a robot described, in order"""
    steps_per_body: Counter = field(default_factory=Counter)
    """transitions per body label"""
    ppo_steps: int = 0
    """transitions with their behaviour log-prob (policy_info)"""
    batch: TransitionBatch = field(default_factory=TransitionBatch.empty)
    task: str = "swimmer"
    """the transitions' task (``bag_task``): ``swimmer``, or ``ant`` (a legged body); several: joined by commas"""

    def as_dict(self) -> dict:
        return {
            "path": self.path,
            "task": self.task,
            "steps_terminated": int(self.batch.terminated.sum()),
            "topics": [{"topic": t, "type": ty, "messages": n} for t, ty, n in self.topics],
            "rejected": {f"{topic}: {reason}": n for (topic, reason), n in sorted(self.rejected.items())},
            "warnings": list(self.warnings),
            "episodes": self.stats.episodes,
            "boundaries": {c: getattr(self.stats, f"boundaries_{c}") for c in StreamStats.BOUNDARY_CAUSES},
            "states": self.stats.states,
            "resent_states": self.stats.resent_states,
            "steps": self.stats.transitions,
            "steps_usable_for_ppo": self.ppo_steps,
            "steps_without_policy_info": self.stats.without_policy_info,
            "steps_applied_unverified": self.stats.applied_unverified,
            "steps_per_chain": {str(n): c for n, c in sorted(self.steps_per_chain.items())},
            "robot_description": {"messages": self.descriptions, "bodies": list(self.described)},
            "steps_per_body": dict(self.steps_per_body),
            "skipped_steps": self.skips.steps(),
            "unused_messages": self.skips.messages(),
        }


def summarize_bag(
    path: str | Path, config: TransitionConfig, namespace: str | None = None, joint_map: JointMap | None = None
) -> BagSummary:
    """Read one bag and turn it into transitions (raises ``BagError`` for a bag that cannot be read).
    ``joint_map``: the robot until the bag's robot_description says otherwise (``TransitionAssembler``);
    default ``bag_robot``'s."""
    config = bag_config(path, config, namespace)
    reader = BagReader(path, namespace=namespace)
    asm = TransitionAssembler(config, bag_robot(path, namespace) if joint_map is None else joint_map)
    transitions, described = [], {}
    for record in reader.records():
        transitions += asm.push(record)
        if isinstance(record, DescriptionRecord) and not asm.joint_map.is_fallback:
            described.setdefault(described_body(record.text, asm.joint_map.robot.tree))
    transitions += asm.flush()
    batch = TransitionBatch.from_transitions(transitions)
    stats = reader.stats
    logical = reader.logical_names(reader.namespaces[0])
    topics = []
    for name, info in sorted(reader.topics.items()):
        if name in logical:
            key = logical[name]
            count = stats.counts[key] + sum(n for (t, _), n in stats.rejected.items() if t == key)
        else:
            count = stats.skipped[name]
        topics.append((name, info.msgtype, count))
    return BagSummary(
        path=str(path),
        topics=topics,
        rejected=Counter(stats.rejected),
        warnings=list(stats.warnings),
        skips=asm.skips,
        stats=asm.stats,
        steps_per_chain=Counter(batch.num_joints.tolist()),
        descriptions=stats.counts[DESCRIPTION_TOPIC],
        described=list(described),
        steps_per_body=Counter(batch.steps_per_body()),
        ppo_steps=int(batch.has_policy_info.sum()),
        batch=batch,
        task=config.task,
    )


def bag_task(path: str | Path, namespace: str | None = None) -> str:
    """The task of a bag's transitions (``protocol.transitions.TASKS``): ``ant`` when its first odometry is of a
    body in 3-D (``OdometryRecord.planar`` False: a legged body), else ``swimmer``."""
    for record in BagReader(path, namespace=namespace).records():
        if isinstance(record, OdometryRecord):
            return "swimmer" if record.planar else "ant"
    return "swimmer"


def bag_config(path: str | Path, config: TransitionConfig, namespace: str | None = None) -> TransitionConfig:
    """``config`` for the bag: with the task left at its default, the bag's own (``bag_task``)."""
    if config.task != TransitionConfig.task:
        return config
    return dataclasses.replace(config, task=bag_task(path, namespace))


def described_body(urdf: str, tree) -> str:
    """What a robot_description describes, by what it is: a swimmer by its shape (``chain-6``, ``star-3x2``), a
    centipede by its size (``centipede-5``, from the sim's robot name), any other robot by its URDF name and its
    tree's shape (Gymnasium's ant: ``robot 'ant' (star-4x2 tree)``, not a swimmer ``star-4x2``)."""
    match = re.search(r"<robot\b[^>]*\bname\s*=\s*([\"'])(.*?)\1", urdf[:4096])
    name = match.group(2) if match else ""
    shape = body_label(tree)
    if not name or name.startswith("swimmer"):
        return shape
    if (size := re.fullmatch(r"centipede(\d+)", name)) is not None:
        return f"centipede-{size.group(1)}"
    return f"robot {name!r} ({shape} tree)"


def bag_robot(path: str | Path, namespace: str | None = None) -> JointMap | None:
    """The robot of a bag's first states: its first robot_description, if it reads as one (else None: the
    assembler's fallback, chains in message order, until a description in the stream says otherwise)."""
    first = first_description(path, namespace)
    if first is None:
        return None
    try:
        return JointMap.from_urdf(first.text)
    except ValueError:  # no robot: the stream counts it (bad_description) when it reaches it
        return None


def total(summaries: list[BagSummary]) -> BagSummary:
    """The sum over several bags (topics by name, counts added; batches concatenated)."""
    out = BagSummary(path=f"total over {len(summaries)} bags")
    topics: dict[str, tuple[str, int]] = {}
    for s in summaries:
        for name, ty, n in s.topics:
            topics[name] = (ty, topics.get(name, (ty, 0))[1] + n)
        out.rejected.update(s.rejected)
        out.warnings += s.warnings
        out.skips.merge(s.skips)
        out.stats.merge(s.stats)
        out.steps_per_chain.update(s.steps_per_chain)
        out.descriptions += s.descriptions
        out.described += [label for label in s.described if label not in out.described]
        out.steps_per_body.update(s.steps_per_body)
        out.ppo_steps += s.ppo_steps
        out.task = ",".join(dict.fromkeys(s.task for s in summaries))
    out.topics = [(name, ty, n) for name, (ty, n) in sorted(topics.items())]
    out.batch = TransitionBatch.concatenate([s.batch for s in summaries])
    return out


def format_summary(s: BagSummary) -> str:
    lines = [f"{s.path}"]
    width = max((len(t) for t, _, _ in s.topics), default=0)
    lines.append("  topics:")
    lines += [f"    {t:<{width}}  {n:>8}  {ty}" for t, ty, n in s.topics] or ["    none"]
    if s.rejected:
        lines.append("  undecodable messages: " + _counts({f"{t} ({r})": n for (t, r), n in s.rejected.items()}))
    if s.descriptions:
        bodies = ", ".join(s.described) or "none that reads as a robot"
        lines.append(f"  robot_description: {s.descriptions} ({bodies})")
    else:
        lines.append(f"  {NO_DESCRIPTION}")
    st = s.stats
    boundaries = {c.replace("_", " "): getattr(st, f"boundaries_{c}") for c in StreamStats.BOUNDARY_CAUSES}
    lines.append(
        f"  states: {st.states} ({st.resent_states} re-sent); episode boundaries: {_counts(boundaries) or 'none'}"
    )
    lines.append(f"  episodes: {st.episodes} (runs of consecutive steps)")
    chains = ", ".join(f"{n} joints: {c}" for n, c in sorted(s.steps_per_chain.items()))
    lines.append(f"  steps: {st.transitions}" + (f" ({chains})" if chains else ""))
    if s.task != "swimmer":  # a legged body's: 12 global features, Ant-v5's reward, falls terminate
        lines.append(f"  task: {s.task} ({int(s.batch.terminated.sum())} episodes ended by a fall)")
    if s.steps_per_body:
        lines.append("  bodies: " + ", ".join(f"{label} {n}" for label, n in s.steps_per_body.items()))
    lines.append(
        f"  usable for PPO: {s.ppo_steps}"
        + (f" ({st.without_policy_info} without policy_info: no behaviour log-prob)" if st.without_policy_info else "")
    )
    if st.applied_unverified:
        lines.append(f"  applied effort not reported by the state (command trusted): {st.applied_unverified}")
    skipped, unused = s.skips.steps(), s.skips.messages()
    lines.append(f"  skipped steps: {_counts(skipped) or 'none'}" + (f" ({why})" if (why := no_steps(s)) else ""))
    lines.append(f"  unused messages: {_counts(unused) or 'none'}")
    lines += [f"  warning: {w}" for w in s.warnings]
    return "\n".join(lines)


def no_steps(s: BagSummary) -> str:
    """Why a bag gave no step when no step was skipped (every step left out is counted under its reason, but a
    bag can hold no step to leave out); '' when it gave steps or the skipped steps say why."""
    st = s.stats
    if st.transitions or s.skips.steps_skipped:
        return ""
    if not st.states:
        return "no joint_states of the robot's topics were read: morph-bag info lists the bag's topics"
    return (f"{st.states} states in {st.episodes} episodes, none followed by a next state of its episode: a step "
            "is a state, its answer and the next state")  # fmt: skip


def _counts(counts: dict) -> str:
    return ", ".join(f"{k} {v}" for k, v in counts.items() if v)


PPO_TOPICS = ("joint_states", "odom")
"""topics a bag must have to train on; a missing policy_info is reported as what PPO lacks
(``MissingPolicyInfoError``), effort_commands may be missing (policy_info holds the action)"""


def read_bags(bags: list[str | Path], namespace: str | None = None) -> tuple[TransitionBatch, list[str], SkipCounts]:
    """The transitions of ``bags`` (each its own stream), the reader's warnings and the steps skipped;
    raises ``BagError`` for a bag that cannot be read."""
    batches, warnings, skips = [], [], SkipCounts()
    for bag in bags:
        reader = BagReader(bag, required=PPO_TOPICS, namespace=namespace)
        config = bag_config(bag, TransitionConfig(), namespace)  # a swimmer's task, or a legged body's
        asm = TransitionAssembler(config, bag_robot(bag, namespace))  # its first states are of its first robot
        batches.append(TransitionBatch.from_transitions(asm.push_many(reader.records()) + asm.flush()))
        warnings += reader.stats.warnings
        skips.merge(asm.skips)
    return TransitionBatch.concatenate(batches), warnings, skips
