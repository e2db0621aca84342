"""Write a rosbag2 bag the way ROS 2 Jazzy does, with ``rosbags``: no ROS import.

Layout: a new folder ``<bag>/`` holding storage files ``<bag>_0.mcap``,
``<bag>_1.mcap``, ... (or ``.db3``; a new one when the current file reaches
``max_bag_size`` bytes or spans ``max_bag_duration_ns`` of log time) and, when
the writer is closed, ``metadata.yaml`` in version 9 (Jazzy's): per topic
its type, serialization format, the publishers' offered QoS profiles and the
type description hash (RIHS01_...).

What survives a kill (SIGKILL, power is another matter):
- MCAP: messages are written in chunks of ``chunk_size`` bytes, each flushed
  to the file when complete; ``flush()`` (the recorder calls it periodically)
  closes a partial chunk. A reader gets every message up to the last
  complete chunk (``bag_io`` reads such a file's valid prefix).
- sqlite3: rosbag2's "resilient" settings (WAL journal, synchronous=NORMAL);
  ``flush()`` commits. Every committed message stays readable.
metadata.yaml is missing after a kill; ``bag_io`` reads the storage files.

The storage files come from rosbags' own MCAP and sqlite3 writers; this
module adds what they leave out: split files, a chosen chunk size, flushing,
Jazzy's channel metadata (``topic_type_hash``) and the bag's metadata.yaml.
"""

from __future__ import annotations

import sqlite3
from dataclasses import dataclass, field
from io import BytesIO, StringIO
from pathlib import Path

from rosbags.interfaces import (
    Connection,
    ConnectionExtRosbag2,
    MessageDefinition,
    MessageDefinitionFormat,
    Qos,
)
from rosbags.rosbag2.enums import CompressionMode
from rosbags.rosbag2.metadata import dump_qos_v9
from rosbags.rosbag2.storage_mcap import Channel, McapWriter, write_channel, write_string
from rosbags.rosbag2.storage_sqlite3 import Sqlite3Writer
from rosbags.typesys import Stores, get_typestore
from ruamel.yaml import YAML

from morph_core.util.atomic import atomic_writer

METADATA_VERSION = 9  # what Jazzy's rosbag2 writes
STORAGE_EXTENSIONS = {"mcap": ".mcap", "sqlite3": ".db3"}
_NO_MESSAGES = 2**63 - 1


class BagWriterError(RuntimeError):
    """The bag cannot be written (it exists already, a bad option, an unknown type); the text says why."""


@dataclass(frozen=True)
class WriterOptions:
    """How the bag is stored. Sizes in bytes, durations in ns; 0 = no limit."""

    storage: str = "mcap"
    max_bag_size: int = 0
    max_bag_duration_ns: int = 0
    chunk_size: int = 256 * 1024
    """MCAP: bytes of messages per chunk, the most a kill can lose beyond the last flush (at most 1 MiB)."""
    ros_distro: str = "jazzy"

    def __post_init__(self):
        if self.storage not in STORAGE_EXTENSIONS:
            raise BagWriterError(f"storage must be one of {sorted(STORAGE_EXTENSIONS)}, not {self.storage!r}")
        if self.max_bag_size < 0 or self.max_bag_duration_ns < 0:
            raise BagWriterError("max_bag_size and max_bag_duration must be >= 0")
        if not 1 <= self.chunk_size <= 2**20:
            raise BagWriterError(f"chunk_size must be in 1..{2**20} bytes, not {self.chunk_size}")


@dataclass(frozen=True)
class BagTopic:
    """One recorded topic: name (absolute), type ``pkg/msg/Type``, what its publishers offered."""

    name: str
    msgtype: str
    offered_qos: tuple[Qos, ...] = ()
    type_hash: str = ""
    """RIHS01_... as the publishers announced it; '' = computed from the message definition"""
    msgdef: str | None = None
    """the ``ros2msg`` text (with its dependencies); None = from the Jazzy type store"""


def qos_yaml(profiles) -> str:
    """Offered QoS profiles as Jazzy stores them in a storage file (a YAML sequence, version-9 enums)."""
    stream = StringIO()
    yaml = YAML(typ="safe")
    yaml.default_flow_style = False
    yaml.dump(dump_qos_v9(list(profiles)), stream)
    return stream.getvalue().strip() if profiles else ""


class _McapFile(McapWriter):
    """rosbags' MCAP writer with a file name of our choosing, a chunk size, a flush per chunk,
    and Jazzy's channel metadata (``offered_qos_profiles`` and ``topic_type_hash``)."""

    def __init__(self, path: Path, chunk_size: int):
        # rosbags names its one file after the folder (<dir>/<dir>.mcap); rosbag2 numbers split
        # files (<dir>/<dir>_<i>.mcap): rename it while open (the handle stays valid).
        super().__init__(path.parent, CompressionMode.NONE)
        self.path.rename(path)
        self.path = path
        self.chunk_size = chunk_size

    def add_connection(self, connection: Connection, offered_qos_profiles: str) -> None:
        metadata = BytesIO()
        for text in ("offered_qos_profiles", offered_qos_profiles, "topic_type_hash", connection.digest):
            write_string(metadata, text)
        channel = Channel(
            connection.id,
            connection.msgtype,
            connection.topic,
            connection.ext.serialization_format,
            metadata.getvalue(),
        )
        self.channels.append(channel)
        self.channel_stats[connection.id] = 0
        write_channel(self.chunk.bio, channel, self.schemas)

    def write(self, connection: Connection, timestamp: int, data: bytes | memoryview) -> None:
        super().write(connection, timestamp, data)  # closes a chunk itself at 1 MiB
        if self.chunk.bio.tell() >= self.chunk_size:
            self.close_chunk()

    def close_chunk(self) -> None:
        super().close_chunk()
        self.bio.flush()  # a complete chunk reaches the file, so a killed recorder keeps it

    def flush(self) -> None:
        if self.chunk.msgs:  # a chunk of schema and channel records only would have no time range
            self.close_chunk()

    def size(self) -> int:
        return self.bio.tell() + self.chunk.bio.tell()


class _Sqlite3File(Sqlite3Writer):
    """rosbags' sqlite3 writer with a file name of our choosing and rosbag2's 'resilient' settings."""

    def __init__(self, path: Path, ros_distro: str):
        # Not super().__init__: it names the file after the folder and keeps the default journal.
        self.path = path
        self.conn = sqlite3.connect(f"file:{path}?mode=rwc", uri=True)
        # WAL + synchronous=NORMAL (rosbag2's "resilient" preset): a kill keeps every committed
        # transaction, and a reader needs no write access to see them.
        self.conn.execute("PRAGMA journal_mode=WAL")
        self.conn.execute("PRAGMA synchronous=NORMAL")
        self.conn.executescript(self.SQLITE_SCHEMA.replace("'rosbags'", f"'{ros_distro}'"))
        self.cursor = self.conn.cursor()
        self._pending = 0  # message bytes not committed yet (in no file so far)

    def write(self, connection: Connection, timestamp: int, data: bytes | memoryview) -> None:
        super().write(connection, timestamp, data)
        self._pending += len(data)

    def flush(self) -> None:
        self.conn.commit()
        self._pending = 0

    def size(self) -> int:
        wal = self.path.with_name(self.path.name + "-wal")
        return self.path.stat().st_size + (wal.stat().st_size if wal.exists() else 0) + self._pending


@dataclass
class _FileStats:
    path: str
    start: int = _NO_MESSAGES
    end: int = 0
    count: int = 0


@dataclass
class _TopicState:
    topic: BagTopic
    connection: Connection
    count: int = 0


@dataclass
class BagWriter:
    """A rosbag2 bag being written: ``add_topic``, ``write``, ``flush`` now and then, ``close``."""

    path: Path
    options: WriterOptions = field(default_factory=WriterOptions)

    def __post_init__(self):
        self.path = Path(self.path)
        if self.path.exists():
            raise BagWriterError(f"{self.path} exists already: not overwriting a bag (choose a new output)")
        self._typestore = get_typestore(Stores.ROS2_JAZZY)
        self._topics: list[_TopicState] = []
        self._files: list[_FileStats] = []
        self._storage: _McapFile | _Sqlite3File | None = None
        self.path.mkdir(parents=True)
        self._open_file()

    # -- writing ------------------------------------------------------------------------
    def add_topic(self, topic: BagTopic) -> int:
        """Register a topic (once per name); returns the id ``write`` takes."""
        if any(t.topic.name == topic.name for t in self._topics):
            raise BagWriterError(f"topic {topic.name} is in the bag already")
        msgdef, rihs01 = self._definition(topic)
        connection = Connection(
            id=len(self._topics) + 1,
            topic=topic.name,
            msgtype=topic.msgtype,
            msgdef=MessageDefinition(MessageDefinitionFormat.MSG, msgdef),
            digest=topic.type_hash or rihs01,
            msgcount=0,
            ext=ConnectionExtRosbag2("cdr", list(topic.offered_qos)),
            owner=self,
        )
        self._topics.append(_TopicState(topic, connection))
        self._register(connection)
        return connection.id

    def write(self, topic_id: int, log_ns: int, data: bytes | memoryview) -> None:
        """Append one serialized (CDR) message received at ``log_ns``."""
        state = self._topics[topic_id - 1]
        current = self._files[-1]
        if current.count and self._split_due(current, log_ns):
            self._next_file()
            current = self._files[-1]
        self._storage.write(state.connection, log_ns, data)
        state.count += 1
        current.count += 1
        current.start = min(current.start, log_ns)
        current.end = max(current.end, log_ns)

    def flush(self) -> None:
        """Make everything written so far survive a kill of this process."""
        if self._storage is not None:
            self._storage.flush()

    def close(self) -> Path:
        """Finish the storage file and write metadata.yaml; returns the bag folder."""
        if self._storage is not None:
            self._close_file()
            with atomic_writer(self.path / "metadata.yaml") as f:
                self._yaml().dump({"rosbag2_bagfile_information": self.metadata()}, f)
        return self.path

    def __enter__(self) -> BagWriter:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # -- what the bag holds -------------------------------------------------------------
    @property
    def message_count(self) -> int:
        return sum(f.count for f in self._files)

    def counts(self) -> dict[str, int]:
        """Messages written per topic."""
        return {t.topic.name: t.count for t in self._topics}

    def metadata(self) -> dict:
        """The ``rosbag2_bagfile_information`` of metadata.yaml, version 9."""
        start = min((f.start for f in self._files if f.count), default=0)
        end = max((f.end for f in self._files if f.count), default=0)
        return {
            "version": METADATA_VERSION,
            "storage_identifier": self.options.storage,
            "duration": {"nanoseconds": end - start},
            "starting_time": {"nanoseconds_since_epoch": start},
            "message_count": self.message_count,
            "topics_with_message_count": [
                {
                    "topic_metadata": {
                        "name": t.topic.name,
                        "type": t.topic.msgtype,
                        "serialization_format": "cdr",
                        "offered_qos_profiles": dump_qos_v9(list(t.topic.offered_qos)),
                        "type_description_hash": t.connection.digest,
                    },
                    "message_count": t.count,
                }
                for t in self._topics
            ],
            "compression_format": "",
            "compression_mode": "",
            "relative_file_paths": [f.path for f in self._files],
            "files": [
                {
                    "path": f.path,
                    "starting_time": {"nanoseconds_since_epoch": f.start if f.count else 0},
                    "duration": {"nanoseconds": f.end - f.start if f.count else 0},
                    "message_count": f.count,
                }
                for f in self._files
            ],
            "custom_data": None,
            "ros_distro": self.options.ros_distro,
        }

    # -- internals ----------------------------------------------------------------------
    def _definition(self, topic: BagTopic) -> tuple[str, str]:
        if topic.msgdef is not None:
            return topic.msgdef, topic.type_hash
        if topic.msgtype not in self._typestore.fielddefs:
            raise BagWriterError(
                f"no definition of {topic.msgtype} for topic {topic.name}: pass BagTopic.msgdef "
                "(the .msg text) or register the type in the writer's type store"
            )
        msgdef, _ = self._typestore.generate_msgdef(topic.msgtype, ros_version=2)
        return msgdef, self._typestore.hash_rihs01(topic.msgtype)

    @property
    def typestore(self):
        """The Jazzy type store used for definitions; register custom types here before ``add_topic``."""
        return self._typestore

    def _split_due(self, current: _FileStats, log_ns: int) -> bool:
        o = self.options
        if o.max_bag_size and self._storage.size() >= o.max_bag_size:
            return True
        return bool(o.max_bag_duration_ns) and log_ns - current.start >= o.max_bag_duration_ns

    def _open_file(self) -> None:
        name = f"{self.path.name}_{len(self._files)}{STORAGE_EXTENSIONS[self.options.storage]}"
        file = self.path / name
        if self.options.storage == "mcap":
            self._storage = _McapFile(file, self.options.chunk_size)
        else:
            self._storage = _Sqlite3File(file, self.options.ros_distro)
        self._files.append(_FileStats(name))
        self._added_types: set[str] = set()
        for state in self._topics:
            self._register(state.connection)

    def _register(self, connection: Connection) -> None:
        if connection.msgtype not in self._added_types:
            self._storage.add_msgtype(connection)
            self._added_types.add(connection.msgtype)
        self._storage.add_connection(connection, qos_yaml(connection.ext.offered_qos_profiles))

    def _close_file(self) -> None:
        stream = StringIO()
        self._yaml().dump(self.metadata(), stream)
        storage, self._storage = self._storage, None
        storage.close(METADATA_VERSION, stream.getvalue().strip())

    def _next_file(self) -> None:
        self._close_file()
        self._open_file()

    @staticmethod
    def _yaml() -> YAML:
        yaml = YAML(typ="safe")
        yaml.default_flow_style = False
        return yaml


# -- what Jazzy's rosbag2 requires of metadata.yaml (rosbag2_storage/yaml.hpp, qos.cpp, version 9) --
_QOS_ENUMS = {
    "history": {"system_default", "keep_last", "keep_all", "unknown"},
    "reliability": {"system_default", "reliable", "best_effort", "unknown", "best_available"},
    "durability": {"system_default", "transient_local", "volatile", "unknown", "best_available"},
    "liveliness": {"system_default", "automatic", "manual_by_topic", "unknown", "best_available"},
}
_QOS_TIMES = ("deadline", "lifespan", "liveliness_lease_duration")


def jazzy_metadata_problems(info: dict) -> list[str]:
    """What in a ``rosbag2_bagfile_information`` mapping Jazzy's ``ros2 bag info/play`` would reject
    (a key its decoder reads that is missing or of the wrong kind); [] when it would accept it."""
    problems: list[str] = []

    def need(d, key, kind, where):
        if d is None:  # its parent is missing: reported there
            return None
        if not isinstance(d, dict) or key not in d:
            problems.append(f"{where}: no {key}")
            return None
        if not isinstance(d[key], kind) or (kind is int and isinstance(d[key], bool)):
            problems.append(f"{where}.{key}: {d[key]!r} is not {getattr(kind, '__name__', kind)}")
            return None
        return d[key]

    if need(info, "version", int, "metadata") != METADATA_VERSION:
        problems.append(f"metadata.version: {info.get('version')!r}, Jazzy writes {METADATA_VERSION}")
    need(info, "storage_identifier", str, "metadata")
    need(need(info, "duration", dict, "metadata"), "nanoseconds", int, "duration")
    need(need(info, "starting_time", dict, "metadata"), "nanoseconds_since_epoch", int, "starting_time")
    need(info, "message_count", int, "metadata")
    for key in ("compression_format", "compression_mode", "ros_distro"):
        need(info, key, str, "metadata")
    paths = need(info, "relative_file_paths", list, "metadata") or []
    for i, f in enumerate(need(info, "files", list, "metadata") or []):
        where = f"files[{i}]"
        need(f, "path", str, where)
        need(need(f, "starting_time", dict, where), "nanoseconds_since_epoch", int, where)
        need(need(f, "duration", dict, where), "nanoseconds", int, where)
        need(f, "message_count", int, where)
    if "custom_data" not in info or not (info["custom_data"] is None or isinstance(info["custom_data"], dict)):
        problems.append("metadata: custom_data missing or not a mapping")
    for i, t in enumerate(need(info, "topics_with_message_count", list, "metadata") or []):
        need(t, "message_count", int, f"topics[{i}]")
        meta = need(t, "topic_metadata", dict, f"topics[{i}]") or {}
        where = f"topics[{i}] ({meta.get('name')})"
        for key in ("name", "type", "serialization_format", "type_description_hash"):
            need(meta, key, str, where)
        if isinstance(meta.get("type_description_hash"), str) and not meta["type_description_hash"].startswith(
            "RIHS01_"
        ):
            problems.append(f"{where}: type_description_hash {meta['type_description_hash']!r} is not RIHS01_...")
        for j, q in enumerate(need(meta, "offered_qos_profiles", list, where) or []):
            qwhere = f"{where}.offered_qos_profiles[{j}]"
            need(q, "depth", int, qwhere)
            need(q, "avoid_ros_namespace_conventions", bool, qwhere)
            for key, allowed in _QOS_ENUMS.items():
                if need(q, key, str, qwhere) not in allowed | {None}:
                    problems.append(f"{qwhere}.{key}: {q[key]!r} is not one of {sorted(allowed)}")
            for key in _QOS_TIMES:
                t_ = need(q, key, dict, qwhere)
                need(t_, "sec", int, f"{qwhere}.{key}")
                need(t_, "nsec", int, f"{qwhere}.{key}")
    if paths and isinstance(info.get("files"), list) and [f.get("path") for f in info["files"]] != paths:
        problems.append("metadata: files[].path differ from relative_file_paths")
    return problems
