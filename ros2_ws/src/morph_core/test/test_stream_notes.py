"""A node's message stream for a live trainer (``protocol.stream_notes``), without DDS: noted only while a reader
is matched, in order, chunked, a late reader given the description first, an oversized message left out."""

from __future__ import annotations

from morph_core.msgs.stream_chunk import MAX_CHUNK_BYTES, unpack_stream_chunk
from morph_core.protocol.stream_notes import StreamNotes


def entries(chunks):
    return [(e.topic, e.log_ns, bytes(e.data)) for chunk in chunks for e in unpack_stream_chunk(chunk)[1]]


def test_nothing_is_noted_before_a_reader_matches():
    notes = StreamNotes(bytes)
    notes.note("joint_states", b"s0", 1)
    assert notes.tick(streaming=False, log_ns=2) == ([], [])
    assert notes.tick(streaming=True, log_ns=3) == ([], [])  # noted from now on, nothing from before


def test_noted_messages_go_out_in_order_at_the_next_tick():
    notes = StreamNotes(bytes)
    notes.tick(streaming=True, log_ns=0)
    notes.note("joint_states", b"state", 1)
    notes.note("effort_commands", b"efforts", 2)
    assert notes.serialize() == ([], [])  # serialized after the answer, into the open chunk
    notes.note("odom", b"odom", 3)
    chunks, errors = notes.tick(streaming=True, log_ns=4)
    assert errors == [] and len(chunks) == 1
    assert entries(chunks) == [("joint_states", 1, b"state"), ("effort_commands", 2, b"efforts"), ("odom", 3, b"odom")]
    notes.tick(streaming=False, log_ns=5)
    notes.note("odom", b"late", 6)
    assert notes.tick(streaming=False, log_ns=7) == ([], [])  # the reader left


def test_a_reader_that_matches_late_gets_the_adopted_description_first():
    notes = StreamNotes(bytes)
    notes.note_description(b"<robot/>", 1)  # no reader: not noted, but kept once adopted
    notes.adopted_description(b"<robot/>")
    notes.tick(streaming=True, log_ns=2)
    notes.note("joint_states", b"state", 3)
    chunks, _ = notes.tick(streaming=True, log_ns=4)
    assert entries(chunks) == [("robot_description", 2, b"<robot/>"), ("joint_states", 3, b"state")]


def test_full_chunks_go_out_at_once_and_an_oversized_message_is_left_out_and_counted():
    notes = StreamNotes(bytes)
    notes.tick(streaming=True, log_ns=0)
    big = b"x" * (MAX_CHUNK_BYTES // 2)
    for k in range(3):
        notes.note("joint_states", big, k)
    notes.note("odom", b"y" * (MAX_CHUNK_BYTES + 1), 9)
    full, errors = notes.serialize()
    assert len(full) == 2 and [e[1] for e in entries(full)] == [0, 1]  # no two fit in one chunk
    assert len(errors) == 1 and errors[0].startswith("not streamed (1 so far): ") and notes.unstreamed == 1
    rest, _ = notes.tick(streaming=True, log_ns=10)
    assert [e[1] for e in entries(rest)] == [2]
