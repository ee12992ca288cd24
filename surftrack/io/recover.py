"""Recovering an unfinished MCAP file: a run killed by SIGKILL, a crash of the machine or a full disk leaves
a file without its summary and footer, which indexed readers (Foxglove, ``mcap.reader.make_reader``)
refuse. :func:`recover_mcap` reads it as a stream, record by record, up to the first record that is
incomplete or corrupt, and writes every message read so far (with its schema, channel, metadata and
attachments) into a new, finished file. Messages inside a chunk that was cut off are lost with that chunk:
an MCAP chunk is compressed as a whole.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass
from pathlib import Path

from mcap.exceptions import EndOfFile, McapError
from mcap.stream_reader import Attachment, Channel, Header, Message, Metadata, Schema, StreamReader
from mcap.writer import MCAP0_MAGIC, CompressionType, Writer

__all__ = ["RecoveredMcap", "recover_mcap"]


@dataclass(frozen=True)
class RecoveredMcap:
    """What :func:`recover_mcap` wrote: message count, channels, first and last log time (ns; 0 when no
    message), the number of input bytes it could read, and why it stopped there ("" when the input was
    read to its end)."""

    messages: int
    channels: int
    start_ns: int
    end_ns: int
    bytes_read: int
    stopped: str


class _CountingFile:
    """A binary file that counts the bytes read from it (how far the stream reader got)."""

    def __init__(self, f):
        self._f, self.position = f, 0

    def read(self, n: int = -1) -> bytes:
        data = self._f.read(n)
        self.position += len(data)
        return data


def recover_mcap(broken: str | Path, fixed: str | Path) -> RecoveredMcap:
    """Copy every readable record of the MCAP file ``broken`` into a new, finished MCAP file ``fixed``
    (zstd chunks). Raises ``ValueError`` (one line naming the file) when ``broken`` is not an MCAP file or
    when ``fixed`` is ``broken``; ``OSError`` when either cannot be opened."""
    broken, fixed = Path(broken), Path(fixed)
    if fixed.resolve() == broken.resolve():
        raise ValueError(f"{fixed}: the recovered file must not overwrite the file it is recovered from")
    schemas: dict[int, int] = {}  # id in broken -> id in fixed
    channels: dict[int, int] = {}
    count, start, end, stopped = 0, 0, 0, ""
    with open(broken, "rb") as raw:
        if raw.read(len(MCAP0_MAGIC)) != MCAP0_MAGIC:
            raise ValueError(f"{broken}: not an MCAP file (it does not start with the MCAP magic bytes)")
        raw.seek(0)
        src = _CountingFile(raw)
        records = StreamReader(src, skip_magic=False, emit_chunks=False, validate_crcs=True).records
        try:
            first = next(records)
        except (McapError, struct.error, EOFError, ValueError) as e:
            raise ValueError(f"{broken}: not an MCAP file ({_why(e)})") from None
        if not isinstance(first, Header):
            raise ValueError(f"{broken}: not an MCAP file (no header record)")
        with open(fixed, "wb") as out:
            writer = Writer(out, compression=CompressionType.ZSTD)
            writer.start(profile=first.profile, library=first.library or "surftrack recover")
            try:
                for rec in records:
                    # a finished file's summary section repeats every schema and channel: register each once
                    if isinstance(rec, Schema) and rec.id not in schemas:
                        schemas[rec.id] = writer.register_schema(rec.name, rec.encoding, rec.data)
                    elif isinstance(rec, Channel) and rec.id not in channels:
                        channels[rec.id] = writer.register_channel(rec.topic, rec.message_encoding,
                                                                   schemas.get(rec.schema_id, 0), rec.metadata)
                    elif isinstance(rec, Message) and rec.channel_id in channels:
                        writer.add_message(channels[rec.channel_id], rec.log_time, rec.data, rec.publish_time,
                                           rec.sequence)
                        start = rec.log_time if count == 0 else min(start, rec.log_time)
                        end = max(end, rec.log_time)
                        count += 1
                    elif isinstance(rec, Metadata):
                        writer.add_metadata(rec.name, rec.metadata)
                    elif isinstance(rec, Attachment):
                        writer.add_attachment(rec.create_time, rec.log_time, rec.name, rec.media_type, rec.data)
            except Exception as e:  # noqa: BLE001 - whatever the damage, what was read so far is kept
                stopped = _why(e)
            finally:
                writer.finish()
    return RecoveredMcap(count, len(channels), start, end, src.position, stopped)


def _why(e: BaseException) -> str:
    """One line for a reading error: running out of bytes reads as truncation."""
    if isinstance(e, (EndOfFile, struct.error, EOFError)):
        return "the file ends inside a record"
    text = str(e).strip().splitlines()[0] if str(e).strip() else ""
    return f"{e.__class__.__name__}: {text}" if text else e.__class__.__name__
