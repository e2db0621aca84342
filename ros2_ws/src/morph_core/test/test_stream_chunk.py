"""stream_chunks layout: chunks keep their entries in order, stay within their size, and refuse damage."""

import pytest

from morph_core.msgs.stream_chunk import (
    MAX_CHUNK_BYTES,
    TOPICS,
    ChunkWriter,
    StreamChunkError,
    StreamEntry,
    unpack_stream_chunk,
)


def test_entries_come_back_in_order_with_the_sequence():
    writer = ChunkWriter()
    sent = [StreamEntry(TOPICS[i % len(TOPICS)], 1_000 + i, bytes([i]) * (i + 1)) for i in range(12)]
    for e in sent[:5]:
        assert writer.add(e.topic, e.log_ns, e.data) is None
    assert len(writer) == 5
    first = writer.take()
    assert writer.take() is None and len(writer) == 0
    for e in sent[5:]:
        writer.add(e.topic, e.log_ns, e.data)
    assert unpack_stream_chunk(first) == (0, sent[:5])
    assert unpack_stream_chunk(writer.take()) == (1, sent[5:])


def test_a_chunk_goes_out_before_it_would_pass_its_size():
    writer = ChunkWriter(max_bytes=200)
    out = [c for c in (writer.add("joint_states", i, b"x" * 50) for i in range(10)) if c is not None]
    out.append(writer.take())
    assert all(len(c) <= 200 for c in out)
    entries = [e for c in out for e in unpack_stream_chunk(c)[1]]
    assert [e.log_ns for e in entries] == list(range(10))
    assert [unpack_stream_chunk(c)[0] for c in out] == list(range(len(out)))
    assert len(out) == 5  # a 16-byte header + 3 x (13 + 50) = 205 > 200: two entries per chunk
    with pytest.raises(ValueError, match="does not fit"):
        writer.add("odom", 0, b"x" * 200)
    assert ChunkWriter().max_bytes == MAX_CHUNK_BYTES


@pytest.mark.parametrize(
    "damage, reason",
    [
        (lambda c: c[:10], "shorter than the chunk header"),
        (lambda c: b"XXXX" + c[4:], "not a stream chunk"),
        (lambda c: c[:-3], "announced"),
        (lambda c: c + b"\0", "after the last"),
        (lambda c: c[:16] + bytes([len(TOPICS)]) + c[17:], "unknown topic index"),
        (lambda c: c[:12] + (5).to_bytes(4, "little") + c[16:], "cut off in entry 2"),
    ],
)
def test_damaged_chunks_are_refused_with_the_reason(damage, reason):
    writer = ChunkWriter()
    writer.add("joint_states", 1, b"abc")
    writer.add("policy_info", 2, b"defg")
    chunk = writer.take()
    with pytest.raises(StreamChunkError, match=reason):
        unpack_stream_chunk(damage(chunk))
