"""The layout of ``stream_chunks``: a pair's message stream, as its policy node saw it, a few dozen steps at a time.

A live trainer listening to a lockstep pair's four data topics wakes four
times per control step and is one more reader of every message: on a machine
whose cores the pairs already fill, that costs the loops a large share of
their rate (docs/benchmarks.md). The policy node sees the whole stream anyway
(it receives ``episode_start``, ``robot_description``, ``joint_states`` and
``odom`` and sends ``effort_commands`` and ``policy_info``), so it can hand it
over in chunks:
one message per ``MAX_CHUNK_BYTES`` or per period, each message inside it
serialized exactly as on the wire (CDR), in the order the node received or
sent it. A trainer decodes them with the same decoders as a bag and feeds
the same assembler.

On the wire it is a standard ``std_msgs/msg/UInt8MultiArray`` whose data is

    header   b"MSC1", sequence (u64), entry count (u32)       little-endian
    entries  topic index (u8), log time ns (i64), length (u32), CDR bytes

with the topic index into ``TOPICS``. The sequence counts the node's chunks
from 0, so a reader can count chunks it lost. ``ChunkWriter`` builds them,
``unpack_stream_chunk`` checks and splits one (``StreamChunkError`` for
anything malformed).
"""

from __future__ import annotations

import struct
from dataclasses import dataclass

TOPIC = "stream_chunks"
"""the chunks' topic, relative to a pair's namespace (published by its policy node)"""
TOPICS = ("episode_start", "joint_states", "odom", "effort_commands", "policy_info", "robot_description")
"""the topics a chunk carries, by index (new ones are appended: a chunk's indices keep their meaning)"""
MAX_CHUNK_BYTES = 60_000
"""a chunk goes out before it would grow past this: one UDP datagram, never a fragmented sample (a
reliable Fast DDS reader can wedge on those, docs/design.md)"""
_MAGIC = b"MSC1"
_HEADER = struct.Struct("<4sQI")
_ENTRY = struct.Struct("<BqI")


class StreamChunkError(ValueError):
    """A chunk that does not fit the layout; ``str(err)`` is the reason."""


@dataclass(frozen=True)
class StreamEntry:
    topic: str
    """one of ``TOPICS``"""
    log_ns: int
    """when the policy node received (or sent) it"""
    data: bytes
    """the message, CDR-serialized"""


def unpack_stream_chunk(data: bytes | bytearray | memoryview) -> tuple[int, list[StreamEntry]]:
    """(sequence, entries) of one chunk's data; raises ``StreamChunkError`` naming what is wrong."""
    data = memoryview(data).cast("B")
    if len(data) < _HEADER.size:
        raise StreamChunkError(f"{len(data)} bytes: shorter than the chunk header")
    magic, seq, count = _HEADER.unpack_from(data)
    if magic != _MAGIC:
        raise StreamChunkError(f"not a stream chunk (starts {bytes(magic)!r})")
    entries, off = [], _HEADER.size
    for i in range(count):
        if off + _ENTRY.size > len(data):
            raise StreamChunkError(f"cut off in entry {i} of {count}")
        index, log_ns, size = _ENTRY.unpack_from(data, off)
        off += _ENTRY.size
        if index >= len(TOPICS):
            raise StreamChunkError(f"entry {i}: unknown topic index {index}")
        if off + size > len(data):
            raise StreamChunkError(f"entry {i}: {size} bytes announced, {len(data) - off} left")
        entries.append(StreamEntry(TOPICS[index], log_ns, bytes(data[off : off + size])))
        off += size
    if off != len(data):
        raise StreamChunkError(f"{len(data) - off} bytes after the last of {count} entries")
    return seq, entries


class ChunkWriter:
    """Collects serialized messages into chunks: ``add`` each, ``take`` a finished chunk's data."""

    def __init__(self, max_bytes: int = MAX_CHUNK_BYTES):
        if max_bytes <= _HEADER.size + _ENTRY.size:
            raise ValueError(f"max_bytes must exceed {_HEADER.size + _ENTRY.size}, got {max_bytes}")
        self.max_bytes = max_bytes
        self.sequence = 0
        """the sequence number of the next chunk"""
        self._parts: list[bytes] = []
        self._count = 0
        self._size = _HEADER.size
        self._index = {topic: i for i, topic in enumerate(TOPICS)}

    def __len__(self) -> int:
        """entries waiting for the next chunk"""
        return self._count

    def add(self, topic: str, log_ns: int, data: bytes) -> bytes | None:
        """Add one message; returns the chunk that had to go out first to keep within ``max_bytes`` (else
        None). A message too large for any chunk raises ``ValueError``."""
        size = _ENTRY.size + len(data)
        if _HEADER.size + size > self.max_bytes:
            raise ValueError(f"a {topic} message of {len(data)} bytes does not fit a chunk of {self.max_bytes}")
        full = self.take() if self._size + size > self.max_bytes else None
        self._parts += (_ENTRY.pack(self._index[topic], log_ns, len(data)), data)
        self._count += 1
        self._size += size
        return full

    def take(self) -> bytes | None:
        """The chunk of the entries added since the last one (None if there are none)."""
        if not self._count:
            return None
        chunk = b"".join([_HEADER.pack(_MAGIC, self.sequence, self._count), *self._parts])
        self.sequence += 1
        self._parts, self._count, self._size = [], 0, _HEADER.size
        return chunk
