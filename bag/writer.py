"""A ROS 2 MCAP writer over mcap-ros2-support: messages as dicts (or decoded objects), schemas from ``msgdefs``."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from streamdet.bag.deps import require
from streamdet.bag.msgdefs import full_name, schema_text


class BagWriter:
    """Writes one ``.mcap`` file (profile ros2, CDR messages, zstd chunks); use as a context manager."""

    def __init__(self, path: str | Path) -> None:
        writer_mod = require("mcap_ros2.writer")
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._file = open(self.path, "wb")
        self._writer = writer_mod.Writer(self._file)
        self._schemas: dict[str, Any] = {}
        self.count = 0

    def schema(self, datatype: str, text: str | None = None) -> Any:
        """The registered schema of ``datatype`` (``pkg/msg/Type``); ``text`` None: streamdet's own definition."""
        name = full_name(datatype)
        if name not in self._schemas:
            self._schemas[name] = self._writer.register_msgdef(name, text if text is not None else schema_text(name))
        return self._schemas[name]

    def write(self, topic: str, datatype: str, message: Any, log_time_ns: int) -> None:
        stamp = int(log_time_ns)
        self._writer.write_message(topic, self.schema(datatype), message, log_time=stamp, publish_time=stamp)
        self.count += 1

    def metadata(self, name: str, data: dict[str, str]) -> None:
        self._writer.add_metadata(name, data)

    def close(self) -> None:
        try:
            self._writer.finish()
        finally:
            self._file.close()

    def __enter__(self) -> "BagWriter":
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()
