"""A ROS 2 MCAP writer over mcap-ros2-support: messages as dicts (or decoded objects), schemas from ``msgdefs``."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

from streamdet.bag.deps import require
from streamdet.bag.msgdefs import full_name, schema_text
from streamdet.core.file_output import open_beside


class BagWriter:
    """Writes one ``.mcap`` file (profile ros2, CDR messages, zstd chunks); use as a context manager.

    The bag is written to a hidden temporary file beside ``path`` and renamed onto ``path`` only once it is complete:
    a failed or interrupted write then leaves neither a partial bag nor a truncated file at ``path`` (which may have
    been an input the export was still reading). Leaving the ``with`` block by an exception removes the temporary.
    """

    def __init__(self, path: str | Path) -> None:
        writer_mod = require("mcap_ros2.writer")
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self.tmp_path, self._file = open_beside(self.path, suffix=".partial")
        try:
            self._writer = writer_mod.Writer(self._file)
        except BaseException:
            self._discard()
            raise
        self._schemas: dict[str, Any] = {}
        self._topics: set[str] = set()  # topics with a channel
        self.count = 0
        self._closed = False

    def schema(self, datatype: str, text: str | None = None) -> Any:
        """The registered schema of ``datatype`` (``pkg/msg/Type``); ``text`` None: streamdet's own definition."""
        name = full_name(datatype)
        if name not in self._schemas:
            self._schemas[name] = self._writer.register_msgdef(name, text if text is not None else schema_text(name))
        return self._schemas[name]

    def write(self, topic: str, datatype: str, message: Any, log_time_ns: int,
              channel_metadata: dict[str, str] | None = None) -> None:  # fmt: skip
        """One message. ``channel_metadata``: the channel's, with the topic's first message (a copied bag's recorded
        ``offered_qos_profiles``, which ``ros2 bag play`` offers again: a latched /tf_static stays latched)."""
        stamp = int(log_time_ns)
        schema = self.schema(datatype)
        if channel_metadata and topic not in self._topics:
            self._register_channel(topic, schema, channel_metadata)
        self._topics.add(topic)
        self._writer.write_message(topic, schema, message, log_time=stamp, publish_time=stamp)
        self.count += 1

    def _register_channel(self, topic: str, schema: Any, metadata: dict[str, str]) -> None:
        # mcap_ros2's Writer registers a channel on a topic's first message, without metadata, and has no call that
        # takes any: the channel is registered here the same way (CDR, its schema) and handed to it by topic
        inner, ids = getattr(self._writer, "_writer", None), getattr(self._writer, "_channel_ids", None)
        if inner is None or not isinstance(ids, dict):
            raise RuntimeError("mcap_ros2.writer.Writer no longer keeps _writer / _channel_ids: the channel metadata of "
                               f"{topic} cannot be written (bag/writer.py needs updating for this mcap-ros2-support)")
        ids[topic] = inner.register_channel(topic=topic, message_encoding="cdr", schema_id=schema.id,
                                            metadata={str(k): str(v) for k, v in metadata.items()})  # fmt: skip

    def metadata(self, name: str, data: dict[str, str]) -> None:
        self._writer.add_metadata(name, data)

    def close(self) -> None:
        """Finish the bag and move it onto ``path``; on any failure the temporary is removed and ``path`` untouched."""
        if self._closed:
            return
        self._closed = True
        try:
            self._writer.finish()
            self._file.close()
            os.replace(self.tmp_path, self.path)
        except BaseException:
            self._discard()
            raise

    def abort(self) -> None:
        """Drop what was written: the temporary goes, ``path`` stays as it was."""
        if not self._closed:
            self._closed = True
            self._discard()

    def _discard(self) -> None:
        try:
            self._file.close()
        finally:
            self.tmp_path.unlink(missing_ok=True)

    def __enter__(self) -> "BagWriter":
        return self

    def __exit__(self, exc_type: Any, *exc: Any) -> None:
        if exc_type is None:
            self.close()
        else:
            self.abort()
