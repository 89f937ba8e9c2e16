"""Keep an MCAP writer's chunk indexes on disk until the summary is written, so its memory stays flat.

mcap's ``Writer`` keeps one ``ChunkIndex`` object per finished chunk in a list and writes them all
into the file's summary at ``finish()``. Our writer finishes a chunk at every flush (every 200
messages or every second, so a killed recorder loses little), and each index holds a dict with one
entry per channel: about 0.7 kB per chunk, which made the recorder's memory creep ~15 B per decision
step over long runs (issue 12). :class:`SpilledChunkIndexes` stands in for that list: every index is
serialised into an anonymous temporary file the moment it is appended, and read back, all at once,
only when the summary is written -- whose buffer holds it then anyway.

It relies on the one way the pinned mcap writer (``constraints.txt``) uses the list: ``append`` when
a chunk is finished, one ``for index in ...: index.write(summary_builder)`` loop at ``finish()``;
:func:`spill_chunk_indexes` checks that the attribute exists and is a list before replacing it, and
otherwise leaves the writer as it is (memory then grows as before, nothing else changes).
"""

from __future__ import annotations

import logging
import os
import tempfile
from collections.abc import Iterator
from typing import Any

from mcap.data_stream import RecordBuilder

__all__ = ["SpilledChunkIndexes", "spill_chunk_indexes"]

log = logging.getLogger(__name__)

#: where mcap's Writer keeps its chunk indexes (a name-mangled private attribute)
_ATTRIBUTE = "_Writer__chunk_indices"


class _SerializedRecords:
    """Records already serialised: ``write`` copies their bytes into the summary."""

    def __init__(self, data: bytes) -> None:
        self.data = data

    def write(self, builder: RecordBuilder) -> None:
        builder.write(self.data)


class SpilledChunkIndexes(list):  # type: ignore[type-arg]
    """A list-like sink for ``ChunkIndex`` records that keeps their serialised bytes in a temporary file."""

    def __init__(self, directory: str | os.PathLike[str] | None = None) -> None:
        super().__init__()
        self._file: Any = tempfile.TemporaryFile(dir=directory)  # anonymous: gone with the process, crash or not
        self._count = 0
        self._builder = RecordBuilder()

    def append(self, record: Any) -> None:
        record.write(self._builder)
        self._file.write(self._builder.end())
        self._count += 1

    def __len__(self) -> int:
        return self._count

    def __bool__(self) -> bool:
        return self._count > 0

    def __iter__(self) -> Iterator[_SerializedRecords]:
        if self._count:
            self._file.flush()
            self._file.seek(0)
            data = self._file.read()
            self._file.seek(0, os.SEEK_END)
            yield _SerializedRecords(data)

    def close(self) -> None:
        self._file.close()


def spill_chunk_indexes(writer: Any, directory: str | os.PathLike[str] | None = None) -> SpilledChunkIndexes | None:
    """Replace ``writer``'s in-memory chunk index list by a :class:`SpilledChunkIndexes` (before any chunk
    is written); None, with a debug line, if this mcap version keeps them some other way."""
    current = getattr(writer, _ATTRIBUTE, None)
    if type(current) is not list or current:
        log.debug("mcap Writer has no empty %s list; chunk indexes stay in memory", _ATTRIBUTE)
        return None
    spilled = SpilledChunkIndexes(directory)
    setattr(writer, _ATTRIBUTE, spilled)
    return spilled
