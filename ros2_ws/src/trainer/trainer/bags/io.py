"""Read rosbag2 bags into the trainer's plain records (``morph_core.msgs.records``), in log-time order.

    reader = BagReader(["bags/run1", "bags/run2"], required=("joint_states", "policy_info"))
    for record in reader.records(): ...
    reader.stats.counts, reader.stats.rejected, reader.stats.warnings

Input: bag folders (with or without metadata.yaml: a killed recorder leaves
none), or storage files (``.mcap``, ``.db3``); split bags are one folder.
Any rosbag2 writer's bags work (``ros2 bag record``, rosbags, ``morph-record``):
only what rosbag2 stores is used (topic name and type, log time, CDR data,
the message definitions for types the Jazzy type store lacks).

Topics are found relative to a namespace (given, or taken from the one
``.../joint_states`` topic) and decoded by the ROS codec (``trainer.codec``: its
table says which type becomes which record); the episode announcement may be
any stamped type (``episode_start_record``).

Other topics (``/clock``, ...) are counted in ``stats.skipped``. A message
that cannot be decoded is counted in ``stats.rejected`` by (topic, reason),
never raised. Bad input raises ``BagError`` naming the file and the
problem: no such path, not a bag, a required topic missing, a topic of the
wrong type. A storage file cut off mid-write (an MCAP file without its
footer) is read up to its last complete chunk, with a warning.
"""

from __future__ import annotations

import heapq
import re
import sqlite3
import struct
from collections import Counter
from collections.abc import Iterable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path

from rosbags.rosbag2.errors import ReaderError
from rosbags.rosbag2.storage_mcap import McapReader, decompress
from rosbags.typesys import Stores, get_types_from_idl, get_types_from_msg, get_typestore
from ruamel.yaml import YAML
from ruamel.yaml.error import YAMLError

from morph_core.msgs.records import (
    DescriptionRecord,
    Record,
)
from trainer.codec import (
    DATA_TOPIC_TYPES,
    DECODERS,
    DESCRIPTION_TOPIC,
    EPISODE_TOPIC,
    TOPIC_TYPES,
    DecodeError,
    episode_start_record,
)

_MCAP_MAGIC = b"\x89MCAP0\r\n"
_SQLITE_MAGIC = b"SQLite format 3\x00"


class BagError(ValueError):
    """A bag that cannot be read as asked; the text names the file and the problem."""


# -- storage files -----------------------------------------------------------------------------
@dataclass(frozen=True)
class TopicInfo:
    """A topic as a storage file declares it."""

    name: str
    msgtype: str
    msgdef: str = ""
    encoding: str = "ros2msg"
    serialization_format: str = "cdr"


@dataclass
class _Storage:
    """One storage file: its topics, and its messages as (log_ns, topic, data) in log-time order."""

    path: Path
    topics: dict[str, TopicInfo]
    messages: Iterable[tuple[int, str, bytes]]
    warning: str = ""


def _open_mcap(path: Path) -> _Storage:
    reader = McapReader(path)
    try:
        reader.open()
    except ReaderError as err:
        return _scan_mcap(path, str(err))
    topics = {
        c.topic: TopicInfo(
            c.topic, c.msgtype, c.msgdef.data, _msgdef_encoding(c.msgdef.format), c.ext.serialization_format
        )
        for c in reader.connections
    }

    def messages():
        try:
            for connection, log_ns, data in reader.messages(reader.connections):
                yield log_ns, connection.topic, data
        finally:
            reader.close()

    return _Storage(path, topics, messages())


def _msgdef_encoding(fmt) -> str:
    return "ros2idl" if fmt.name == "IDL" else "ros2msg"


class _Truncated(Exception):
    pass


def _scan_mcap(path: Path, why: str) -> _Storage:
    """An MCAP file without a valid summary/footer (a killed writer): every complete record from the start.

    Messages in a chunk count only when the whole chunk is there (and its CRC, if any, matches)."""
    data = path.read_bytes()
    if not data.startswith(_MCAP_MAGIC):
        raise BagError(f"{path}: not an MCAP file (bad magic) ({why})")
    schemas: dict[int, tuple[str, str, str]] = {}
    channels: dict[int, TopicInfo] = {}
    messages: list[tuple[int, int, str, bytes]] = []
    pos, end = len(_MCAP_MAGIC), len(data)
    complete_to = pos
    truncated = False

    def records(buf: bytes, start: int, stop: int):
        while start < stop:
            if stop - start < 9:
                raise _Truncated
            op, size = buf[start], int.from_bytes(buf[start + 1 : start + 9], "little")
            body = start + 9
            if body + size > stop:
                raise _Truncated
            yield op, buf[body : body + size], body + size
            start = body + size

    def handle(op: int, body: bytes) -> None:
        if op == 0x03:  # schema
            sid = int.from_bytes(body[:2], "little")
            name, off = _mcap_string(body, 2)
            encoding, off = _mcap_string(body, off)
            length = int.from_bytes(body[off : off + 4], "little")
            schemas[sid] = (name, encoding, body[off + 4 : off + 4 + length].decode())
        elif op == 0x04:  # channel
            cid, sid = struct.unpack_from("<HH", body)
            topic, off = _mcap_string(body, 4)
            encoding, off = _mcap_string(body, off)
            name, schema_encoding, text = schemas.get(sid, ("", "", ""))
            channels[cid] = TopicInfo(topic, name, text, schema_encoding or "ros2msg", encoding)
        elif op == 0x05:  # message
            cid, _seq, log_ns = struct.unpack_from("<HIQ", body)
            if cid in channels:
                messages.append((log_ns, len(messages), channels[cid].name, body[22:]))

    try:
        for op, body, after in records(data, pos, end):
            if op == 0x0F:  # data end: the summary follows
                break
            if op == 0x06:  # chunk: start, end, uncompressed size, crc, compression, records
                _, _, size, crc = struct.unpack_from("<QQQI", body)
                compression, off = _mcap_string(body, 28)
                length = int.from_bytes(body[off : off + 8], "little")
                inner = decompress(body[off + 8 : off + 8 + length], compression, size, crc)
                for inner_op, inner_body, _ in records(inner, 0, len(inner)):
                    handle(inner_op, inner_body)
            else:
                handle(op, body)
            complete_to = after
    except (_Truncated, ReaderError, struct.error, UnicodeDecodeError):
        truncated = True
    messages.sort(key=lambda m: (m[0], m[1]))
    warning = (
        f"{path}: incomplete MCAP file ({why}); read {len(messages)} messages up to byte {complete_to} "
        f"of {end}{', the rest is cut off mid-record' if truncated else ''}"
    )
    return _Storage(path, {t.name: t for t in channels.values()}, [(t, n, d) for t, _, n, d in messages], warning)


def _mcap_string(buf: bytes, off: int) -> tuple[str, int]:
    length = int.from_bytes(buf[off : off + 4], "little")
    if off + 4 + length > len(buf):
        raise _Truncated
    return buf[off + 4 : off + 4 + length].decode(), off + 4 + length


def _open_sqlite3(path: Path) -> _Storage:
    try:
        # Read-only: a bag is never changed by reading it. A WAL left by a killed writer is still read.
        conn = sqlite3.connect(f"file:{path}?mode=ro", uri=True)
        tables = {r[0] for r in conn.execute("SELECT name FROM sqlite_master WHERE type='table'")}
        if not {"topics", "messages"} <= tables:
            conn.close()
            raise BagError(f"{path}: an SQLite file but not a rosbag2 storage file (no topics/messages tables)")
        rows = conn.execute("SELECT id, name, type, serialization_format FROM topics").fetchall()
        defs = {}
        if "message_definitions" in tables:
            for msgtype, encoding, text in conn.execute(
                "SELECT topic_type, encoding, encoded_message_definition FROM message_definitions"
            ):
                defs[msgtype] = (encoding, text)
    except sqlite3.DatabaseError as err:
        raise BagError(f"{path}: cannot read the sqlite3 storage file: {err}") from None
    names = {tid: name for tid, name, _, _ in rows}
    topics = {}
    for _, name, msgtype, fmt in rows:
        encoding, text = defs.get(msgtype, ("ros2msg", ""))
        topics[name] = TopicInfo(name, msgtype, text, encoding or "ros2msg", fmt)

    def messages():
        try:
            cursor = conn.execute("SELECT topic_id, timestamp, data FROM messages ORDER BY timestamp, id")
            for tid, log_ns, data in cursor:
                if tid in names:
                    yield log_ns, names[tid], data
        finally:
            conn.close()

    return _Storage(path, topics, messages())


def _storage_kind(path: Path) -> str | None:
    if path.suffix == ".mcap":
        return "mcap"
    if path.suffix == ".db3":
        return "sqlite3"
    try:
        with path.open("rb") as f:
            head = f.read(16)
    except OSError:
        return None
    if head.startswith(_MCAP_MAGIC):
        return "mcap"
    if head.startswith(_SQLITE_MAGIC):
        return "sqlite3"
    return None


def _split_index(path: Path) -> tuple[int, str]:
    m = re.search(r"_(\d+)$", path.stem)
    return (int(m.group(1)) if m else -1, path.name)


def storage_files(path: str | Path) -> tuple[list[Path], list[str]]:
    """The storage files of one bag (a folder, its metadata.yaml, or one storage file), and warnings."""
    path = Path(path)
    if not path.exists():
        raise BagError(f"{path}: no such file or directory")
    if path.is_file() and path.name == "metadata.yaml":
        path = path.parent
    if path.is_file():
        if _storage_kind(path) is None:
            raise BagError(f"{path}: not a rosbag2 storage file (neither MCAP nor sqlite3)")
        return [path], []
    meta = path / "metadata.yaml"
    if meta.is_file():
        info = _read_metadata(meta)
        mode = info.get("compression_mode") or ""
        if mode:
            raise BagError(
                f"{meta}: compressed bag (compression_mode {mode!r}); decompress it first "
                "(ros2 bag convert) or record with MCAP chunk compression instead"
            )
        files = [path / Path(p).name for p in info.get("relative_file_paths") or []]
        missing = [str(f) for f in files if not f.is_file()]
        if missing:
            raise BagError(f"{meta}: lists storage files that are not there: {missing}")
        if files:
            return files, []
    found = sorted((p for p in path.iterdir() if p.is_file() and p.suffix in (".mcap", ".db3")), key=_split_index)
    if not found:
        raise BagError(f"{path}: not a rosbag2 bag (no metadata.yaml and no .mcap or .db3 storage file)")
    return found, [f"{path}: no metadata.yaml (a recorder that was killed?): reading its {len(found)} storage file(s)"]


def _read_metadata(meta: Path) -> dict:
    try:
        doc = YAML(typ="safe").load(meta.read_text())
        info = doc["rosbag2_bagfile_information"]
        if not isinstance(info, dict):
            raise TypeError("rosbag2_bagfile_information is not a mapping")
        return info
    except (OSError, YAMLError, KeyError, TypeError) as err:
        raise BagError(f"{meta}: not a rosbag2 metadata file ({type(err).__name__}: {err})") from None


def _open_storage(path: Path) -> _Storage:
    kind = _storage_kind(path)
    if kind == "mcap":
        return _open_mcap(path)
    if kind == "sqlite3":
        return _open_sqlite3(path)
    raise BagError(f"{path}: not a rosbag2 storage file (neither MCAP nor sqlite3)")


# -- the reader ---------------------------------------------------------------------------------
@dataclass
class ReadStats:
    """What reading produced: records per logical topic, rejections by (topic, reason), the rest."""

    counts: Counter = field(default_factory=Counter)
    rejected: Counter = field(default_factory=Counter)
    skipped: Counter = field(default_factory=Counter)
    examples: dict = field(default_factory=dict)
    """one example message per (topic, reason) rejected"""
    warnings: list[str] = field(default_factory=list)


class BagReader:
    """One or several bags read as one stream of records in log-time order."""

    def __init__(
        self,
        paths: str | Path | Sequence[str | Path],
        *,
        required: Sequence[str] = (),
        namespace: str | None = None,
        episode_topic: str = EPISODE_TOPIC,
    ):
        if isinstance(paths, str | Path):
            paths = [paths]
        if not paths:
            raise BagError("no bag given")
        self.stats = ReadStats()
        self.episode_topic = episode_topic
        self._typestore = get_typestore(Stores.ROS2_JAZZY)
        self._streams: list[Iterator[tuple[int, str, str, str | None, bytes]]] = []
        self.topics: dict[str, TopicInfo] = {}
        """every topic of every bag (the first bag's declaration where names repeat)"""
        self.namespaces: list[str] = []
        """per bag, the namespace its topics were read under"""
        for bag in paths:
            files, warnings = storage_files(bag)
            self.stats.warnings += warnings
            opened = [_open_storage(f) for f in files]
            for s in opened:
                if s.warning:
                    self.stats.warnings.append(s.warning)
            bag_topics: dict[str, tuple[TopicInfo, Path]] = {}
            for s in opened:
                for t in s.topics.values():
                    bag_topics.setdefault(t.name, (t, s.path))
            ns = self._namespace(namespace, bag_topics, bag)
            self._check(bag, ns, bag_topics, required)
            self._streams += [_labelled(s, self.logical_names(ns)) for s in opened]
            for name, (t, _) in bag_topics.items():
                self.topics.setdefault(name, t)
            self.namespaces.append(ns)
        self._register_types()

    def records(self) -> Iterator[Record]:
        """Every decodable message of the mapped topics as a record, in log-time order (one pass)."""
        streams, self._streams = self._streams, []
        if not streams:
            raise BagError("BagReader.records() reads the bags once; open a new reader to read again")
        merged = heapq.merge(*streams, key=lambda m: m[0]) if len(streams) > 1 else streams[0]
        for log_ns, topic, msgtype, name, data in merged:
            if name is None:
                self.stats.skipped[topic] += 1
                continue
            try:
                record = self._decode(name, msgtype, log_ns, data)
            except DecodeError as err:
                self.stats.rejected[(name, err.reason)] += 1
                self.stats.examples.setdefault((name, err.reason), str(err))
                continue
            self.stats.counts[name] += 1
            yield record

    def read(self) -> list[Record]:
        return list(self.records())

    # -- internals ------------------------------------------------------------------------------
    def _decode(self, name: str, msgtype: str, log_ns: int, data: bytes) -> Record:
        try:
            msg = self._typestore.deserialize_cdr(data, msgtype)
        except Exception as err:  # rosbags raises plain IndexError/struct.error/KeyError on bad bytes
            raise DecodeError("undecodable CDR", f"{type(err).__name__}: {err}") from None
        if name == self.episode_topic:
            return episode_start_record(msg, log_ns)
        return DECODERS[name](msg, log_ns)

    def _namespace(self, given: str | None, topics: dict, bag) -> str:
        if given is not None:
            return "/" + given.strip("/") if given.strip("/") else ""
        candidates = sorted(n for n in topics if n == "/joint_states" or n.endswith("/joint_states"))
        if len(candidates) > 1:
            raise BagError(f"{bag}: several joint_states topics {candidates}: say which namespace to read")
        return candidates[0][: -len("/joint_states")] if candidates else ""

    def logical_names(self, ns: str) -> dict[str, str]:
        """Full topic name -> logical name (a data topic or the episode announcements) of the topics this reader
        decodes under namespace ``ns``; every other topic of a bag is counted as skipped."""
        return {full_topic_name(ns, n): n for n in (*DATA_TOPIC_TYPES, DESCRIPTION_TOPIC, self.episode_topic)}

    def _check(self, bag, ns: str, topics: dict[str, tuple[TopicInfo, Path]], required: Sequence[str]) -> None:
        for name in required:
            if (full := full_topic_name(ns, name)) not in topics:
                raise BagError(f"{bag}: required topic {full} is not in the bag (it has: {sorted(topics) or 'none'})")
        for name in (*DATA_TOPIC_TYPES, DESCRIPTION_TOPIC):
            expected = TOPIC_TYPES[name]
            found = topics.get(full := full_topic_name(ns, name))
            if found is not None and found[0].msgtype != expected:
                raise BagError(f"{found[1]}: topic {full} has type {found[0].msgtype}, expected {expected}")
        for info, file in topics.values():
            if info.serialization_format != "cdr":
                raise BagError(f"{file}: topic {info.name} is stored as {info.serialization_format!r}, not cdr")

    def _register_types(self) -> None:
        """Types the Jazzy store lacks (a custom announcement message) from the bags' own definitions."""
        for info in self.topics.values():
            if info.msgtype in self._typestore.fielddefs or not info.msgdef:
                continue
            try:
                if info.encoding == "ros2idl":
                    types = get_types_from_idl(info.msgdef)
                else:
                    types = get_types_from_msg(info.msgdef, info.msgtype)
                self._typestore.register(types)
            except Exception as err:  # a definition rosbags cannot parse: its messages are rejected, counted
                self.stats.warnings.append(f"topic {info.name}: cannot use its definition of {info.msgtype}: {err}")


def _labelled(storage: _Storage, logical: dict[str, str]) -> Iterator[tuple[int, str, str, str | None, bytes]]:
    """A storage file's messages as (log_ns, topic, type, logical name or None, data)."""
    types = {name: t.msgtype for name, t in storage.topics.items()}
    try:
        for log_ns, topic, data in storage.messages:
            yield log_ns, topic, types[topic], logical.get(topic), data
    except (ReaderError, sqlite3.DatabaseError) as err:
        raise BagError(f"{storage.path}: unreadable past some point: {err}") from None


def full_topic_name(ns: str, name: str) -> str:
    """A pair's topic ``name`` (relative, or absolute like /clock) under namespace ``ns``."""
    return name if name.startswith("/") else f"{ns}/{name}"


def read_bag(paths, **options) -> tuple[list[Record], ReadStats]:
    """All records of ``paths`` (see ``BagReader``) and the reading statistics."""
    reader = BagReader(paths, **options)
    return reader.read(), reader.stats


def first_description(path: str | Path, namespace: str | None = None) -> DescriptionRecord | None:
    """A bag's first ``robot_description`` (read up to it, no further), or None when the bag has none.

    The robot of the states recorded before it: the sim latches its current URDF, so a recorder receives it
    when its description reader matches the sim's writer, which may be after its state reader did (discovery
    matches endpoint by endpoint). Those first states were published while that URDF was the current one."""
    reader = BagReader(path, namespace=namespace)
    if full_topic_name(reader.namespaces[0], DESCRIPTION_TOPIC) not in reader.topics:
        return None
    records = reader.records()
    try:
        return next((r for r in records if isinstance(r, DescriptionRecord)), None)
    finally:
        records.close()  # the storage files, now
