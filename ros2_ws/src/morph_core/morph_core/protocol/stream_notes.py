"""A node's message stream for a live trainer, without ROS: messages noted as they pass, serialized into chunks
(``msgs.stream_chunk``) after the answer has gone out, and only while a reader is matched.

The policy node notes each message it receives and sends; it serializes the notes after each answer (the loop
waits on the answer, not on this) and on its chunk timer, which also tells whether a reader is matched. A reader
that matches after the robot description arrived gets it first all the same (it is latched). The serializer is
the node's (``rclpy.serialization.serialize_message``), so this module needs no ROS.
"""

from __future__ import annotations

from collections.abc import Callable

from morph_core.msgs.stream_chunk import TOPICS, ChunkWriter

DESCRIPTION = "robot_description"


class StreamNotes:
    """Messages noted for the stream and the chunks they make; ``serialize`` turns a message into its bytes."""

    def __init__(self, serialize: Callable[[object], bytes]):
        self._serialize = serialize
        self._chunks = ChunkWriter()
        self._noted: list[tuple[str, int, object]] = []  # (topic, log ns, message) for the next chunk
        self.streaming = False
        """a reader of the chunks is matched"""
        self.unstreamed = 0
        """messages left out, each larger than a chunk (the trainer sees a gap in the stream there)"""
        self._description: object | None = None  # the current one, for a reader that matches later

    def note(self, topic: str, msg: object, log_ns: int) -> None:
        if self.streaming:
            self._noted.append((topic, log_ns, msg))

    def note_description(self, msg: object, log_ns: int) -> None:
        """A received description: streamed once the chunk layout carries its topic, kept for a later reader."""
        if DESCRIPTION in TOPICS:
            self.note(DESCRIPTION, msg, log_ns)

    def adopted_description(self, msg: object) -> None:
        self._description = msg

    def serialize(self) -> tuple[list[bytes], list[str]]:
        """Serialize the noted messages: the chunks that filled up (to publish) and, for each message left out,
        the line to log."""
        full, errors = [], []
        for topic, log_ns, msg in self._noted:
            try:
                chunk = self._chunks.add(topic, log_ns, self._serialize(msg))
            except ValueError as err:  # larger than a chunk
                self.unstreamed += 1
                errors.append(f"not streamed ({self.unstreamed} so far): {err}")
                continue
            if chunk is not None:
                full.append(chunk)
        self._noted.clear()
        return full, errors

    def tick(self, streaming: bool, log_ns: int) -> tuple[list[bytes], list[str]]:
        """The chunk timer: everything noted goes out now (chunks to publish, lines to log); ``streaming`` says
        whether a reader is matched from now on."""
        full, errors = self.serialize()
        chunk = self._chunks.take()
        if chunk is not None:
            full.append(chunk)
        if streaming and not self.streaming and self._description is not None and DESCRIPTION in TOPICS:
            self._noted.append((DESCRIPTION, log_ns, self._description))  # latched: a late reader gets it first
        self.streaming = streaming
        return full, errors
