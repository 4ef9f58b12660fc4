"""A torn MCAP made whole: the file a killed writer leaves (no summary, no footer, a chunk cut short) does
not open in a seeking reader (the `mcap` package's `make_reader`, Foxglove); `finalise_torn` reads it front
to back as far as it goes (`mcap`'s StreamReader: every record up to the last complete chunk) and writes
every record read (header, schemas, channels, messages with their times and sequence numbers, attachments,
metadata) into a new file with chunk indexes, summary and footer. The new file replaces the torn one
through a temporary file and a rename; the torn original is kept beside it (a hard link where the file
system has them, else a copy), so nothing it held is lost. `flightstack report` runs it on the live MCAP
(flightstack.recording.mcap_live), keeping the original as files.TORN_MCAP_FILE."""

from __future__ import annotations

import contextlib
import os
import shutil
from dataclasses import dataclass
from pathlib import Path

from mcap.reader import make_reader
from mcap.records import Attachment, Channel, Header, Message, Metadata, Schema
from mcap.stream_reader import StreamReader
from mcap.writer import CompressionType, Writer

from flightstack.recording.mcap_writer import CHUNK_BYTES


@dataclass
class Finalised:
    """What `finalise_torn` did: messages recovered, the torn original's path and size (B), where its
    stream read stopped (the reader's words)."""

    messages: int
    torn: Path
    torn_bytes: int
    stopped: str


def opens(path: Path) -> bool:
    """Whether a seeking reader opens `path`: its summary and footer are there and read."""
    try:
        with open(path, "rb") as fh:
            make_reader(fh).get_summary()
    except Exception:  # the reader raises whatever the torn bytes make of a record
        return False
    return True


def finalise_torn(path: Path, torn: Path) -> Finalised | None:
    """Rewrite the torn MCAP `path` whole, the original kept as `torn` (replaced if there is one; module
    docstring); None when `path` opens already. OSError when it cannot be read or written; ValueError when
    not even its header reads (nothing to recover)."""
    path, torn = Path(path), Path(torn)
    if opens(path):
        return None
    tmp = path.with_name(f".{path.name}.finalising-{os.getpid()}")
    try:
        messages, stopped = _rewrite(path, tmp)
        torn.unlink(missing_ok=True)
        try:
            os.link(path, torn)
        except OSError:  # no hard links here (or across a mount): a copy
            shutil.copy2(path, torn)
        torn_bytes = torn.stat().st_size
        os.replace(tmp, path)
    finally:
        with contextlib.suppress(OSError):
            tmp.unlink()
    return Finalised(messages, torn, torn_bytes, stopped)


def _rewrite(src: Path, dst: Path) -> tuple[int, str]:
    """Every record of `src` read front to back into a finished MCAP at `dst` (fsynced); (messages
    written, where the read stopped)."""
    schema_ids: dict[int, int] = {}
    channel_ids: dict[int, int] = {}
    messages = 0
    stopped = "the file ended"
    with open(src, "rb") as fin, open(dst, "wb") as fout:
        records = StreamReader(fin, skip_magic=False).records
        try:
            first = next(records)
        except Exception as exc:
            raise ValueError(f"not an MCAP file, or no header ({type(exc).__name__}: {exc})") from None
        if not isinstance(first, Header):
            raise ValueError(f"its first record is {type(first).__name__}, not a header")
        writer = Writer(fout, chunk_size=CHUNK_BYTES, compression=CompressionType.ZSTD)
        writer.start(profile=first.profile, library=first.library)
        try:
            for rec in records:
                if isinstance(rec, Schema):
                    if rec.id not in schema_ids:
                        schema_ids[rec.id] = writer.register_schema(rec.name, rec.encoding, rec.data)
                elif isinstance(rec, Channel):
                    if rec.id not in channel_ids:
                        channel_ids[rec.id] = writer.register_channel(
                            rec.topic, rec.message_encoding, schema_ids.get(rec.schema_id, 0), rec.metadata
                        )
                elif isinstance(rec, Message) and rec.channel_id in channel_ids:
                    channel = channel_ids[rec.channel_id]
                    writer.add_message(channel, rec.log_time, rec.data, rec.publish_time, rec.sequence)
                    messages += 1
                elif isinstance(rec, Attachment):
                    writer.add_attachment(rec.create_time, rec.log_time, rec.name, rec.media_type, rec.data)
                elif isinstance(rec, Metadata):
                    writer.add_metadata(rec.name, rec.metadata)
        except Exception as exc:  # the torn end: whatever the cut bytes make of a record
            stopped = f"{type(exc).__name__}: {exc}"
        writer.finish()
        fout.flush()
        os.fsync(fout.fileno())
    return messages, stopped
