"""The Falconry recording format: MCAP, readable by the mcap CLI and viewers elsewhere.

Layout of a file written by `McapRecordWriter`:
- profile "falconry"; one metadata record "falconry" (key expressions recorded, format notes);
- one channel per key expression actually seen (topic = the key, e.g. falconry/uav1/points),
  message encoding "msgpack" (the payload exactly as it went over Zenoh), channel metadata
  `catalogue` = the catalogue pattern it matched;
- one schema per message type, encoding "jsonschema", named "falconry.<Type>", data = the
  msgspec JSON Schema of the type (keys not in the catalogue get no schema);
- per message: log_time = wall-clock receive time (ns since the Unix epoch), publish_time =
  header.stamp (mission ns) when the payload carries a Header (else the receive time),
  sequence = header.seq (low 32 bits);
- zstd-compressed chunks (1 MiB, and at least one per `flush()`), message indexes and a summary.

File order is receive order; replay follows it (log_time could go backwards with the wall clock).

`read_recording` streams a file without needing its summary, so a file cut short by a crash
yields every message of its complete chunks and reports where the damaged tail starts.
"""
from __future__ import annotations

import json
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import BinaryIO, Callable, Iterator

import msgspec
from mcap.exceptions import EndOfFile, InvalidMagic, RecordLengthLimitExceeded
from mcap.records import Channel, Chunk, Footer, Message
from mcap.stream_reader import StreamReader, breakup_chunk
from mcap.writer import CompressionType, Writer

from schemas.catalogue import catalogue_entry
from schemas.messages import Header
from services.lib.runtime.errors import UsageError

PROFILE = "falconry"
MESSAGE_ENCODING = "msgpack"
SCHEMA_ENCODING = "jsonschema"
COMPRESSIONS = {"zstd": CompressionType.ZSTD, "lz4": CompressionType.LZ4, "none": CompressionType.NONE}
CHUNK_SIZE = 1 << 20


class _Stamped(msgspec.Struct):
    header: Header


_stamped = msgspec.msgpack.Decoder(_Stamped)


def header_of(payload: bytes) -> Header | None:
    """The payload's Header, or None when it carries none (other fields are skipped, not decoded)."""
    try:
        return _stamped.decode(payload).header
    except (msgspec.DecodeError, msgspec.ValidationError, ValueError):
        return None


@dataclass
class WriteStats:
    messages: int = 0
    bytes: int = 0
    per_key: dict[str, int] = field(default_factory=dict)


class McapRecordWriter:
    """Writes received messages to an MCAP file. Single-threaded: one caller at a time."""

    def __init__(self, path: str, key_exprs: tuple[str, ...] = (), compression: str = "zstd",
                 chunk_size: int = CHUNK_SIZE) -> None:
        if compression not in COMPRESSIONS:
            raise UsageError(f"unknown compression {compression!r} (choose from {', '.join(COMPRESSIONS)})")
        self.path = str(path)
        self._file = open(self.path, "wb")
        self._writer = Writer(self._file, chunk_size=chunk_size, compression=COMPRESSIONS[compression])
        self._writer.start(profile=PROFILE, library="falconry recorder")
        self._writer.add_metadata("falconry", {
            "key_exprs": json.dumps(list(key_exprs)),
            "message_encoding": "msgpack of the msgspec Structs in schemas/messages.py, as sent over Zenoh",
            "log_time": "wall-clock receive time, ns since the Unix epoch",
            "publish_time": "header.stamp: mission time, ns",
            "started": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
        })
        self._channels: dict[str, int] = {}
        self._schemas: dict[type, int] = {}
        self.stats = WriteStats()
        self._closed = False

    def _channel(self, key: str) -> int:
        channel = self._channels.get(key)
        if channel is None:
            entry = catalogue_entry(key)
            schema_id = 0  # MCAP's "no schema"
            if entry is not None and entry.type is not None:
                schema_id = self._schemas.get(entry.type, 0)
                if not schema_id:
                    schema = json.dumps(msgspec.json.schema(entry.type), sort_keys=True).encode()
                    schema_id = self._writer.register_schema(f"falconry.{entry.type.__name__}", SCHEMA_ENCODING, schema)
                    self._schemas[entry.type] = schema_id
            metadata = {"catalogue": entry.key} if entry is not None else {}
            channel = self._writer.register_channel(key, MESSAGE_ENCODING, schema_id, metadata)
            self._channels[key] = channel
        return channel

    def write(self, key: str, payload: bytes, receive_ns: int) -> None:
        header = header_of(payload)
        publish_ns = header.stamp if header is not None and header.stamp >= 0 else receive_ns
        sequence = header.seq & 0xFFFFFFFF if header is not None else 0
        self._writer.add_message(self._channel(key), log_time=receive_ns, data=payload,
                                 publish_time=publish_ns, sequence=sequence)
        s = self.stats
        s.messages += 1
        s.bytes += len(payload)
        s.per_key[key] = s.per_key.get(key, 0) + 1

    def flush(self) -> None:
        """Close the chunk in progress and hand it to the OS: a crash after this loses nothing before it."""
        self._writer.flush()

    def close(self) -> None:
        if not self._closed:
            self._closed = True
            self._writer.finish()
            self._file.close()


# ---------------------------------------------------------------------------------- reading
@dataclass(frozen=True)
class RecordedMessage:
    key: str
    payload: bytes
    log_time: int
    publish_time: int
    sequence: int


@dataclass
class ReadReport:
    chunks: int = 0  # complete chunks read
    messages: int = 0  # messages yielded (after the key filter)
    complete: bool = False  # the footer was reached: the file was closed properly
    cut_at: int | None = None  # byte offset where the unreadable tail starts
    reason: str = ""  # why the tail could not be read
    size: int = 0  # bytes in the file

    def describe(self, path: str) -> str:
        if self.complete:
            return f"{path}: complete, {self.chunks} chunks, {self.messages} messages"
        return (f"{path} was cut short: unreadable from byte {self.cut_at} of {self.size} ({self.reason}); "
                f"using the {self.chunks} complete chunks before it ({self.messages} messages)")


class _ExactReads:
    """A file whose short reads raise EndOfFile, so a record cut in half is never half-parsed."""

    def __init__(self, file: BinaryIO) -> None:
        self._file = file
        self.position = 0

    def read(self, size: int = -1) -> bytes:
        data = self._file.read(size)
        if size >= 0 and len(data) < size:
            raise EndOfFile()
        self.position += len(data)
        return data


MCAP_MAGIC = b"\x89MCAP0\r\n"


def is_mcap(path: str | Path) -> bool:
    """Does the file start like an MCAP file? (Checked before anything is written for it.)"""
    try:
        with open(path, "rb") as file:
            return file.read(len(MCAP_MAGIC)) == MCAP_MAGIC
    except OSError:
        return False


def check_recording(path: str | Path) -> None:
    """A recording to read: an existing MCAP file, else a one-line UsageError."""
    if not Path(path).is_file():
        raise UsageError(f"no such recording: {path}")
    if not is_mcap(path):
        raise UsageError(f"{path} is not an MCAP file")


def read_recording(path: str, wanted: Callable[[str], bool] | None = None,
                   report: ReadReport | None = None) -> Iterator[RecordedMessage]:
    """Every message of the file in file order (only keys `wanted` says yes to), chunk by chunk.

    Needs no summary or footer: a file cut short by a crash yields exactly the messages of its
    complete chunks (CRC-checked) and records in `report` where and why it stopped."""
    report = report if report is not None else ReadReport()
    channels: dict[int, str] = {}
    keep: dict[int, bool] = {}
    with open(path, "rb") as file:
        file.seek(0, 2)
        report.size = file.tell()
        file.seek(0)
        source = _ExactReads(file)
        records = StreamReader(source, emit_chunks=True, record_size_limit=report.size).records
        good_until = 0
        while True:
            try:
                record = next(records)
                contents = breakup_chunk(record, validate_crc=True) if isinstance(record, Chunk) else [record]
            except StopIteration:
                break
            except Exception as exc:  # whatever the damaged tail looks like, nothing after it is usable
                if isinstance(exc, InvalidMagic):
                    raise UsageError(f"{path} is not an MCAP file") from None
                report.cut_at = good_until
                if not isinstance(exc, (EndOfFile, RecordLengthLimitExceeded)):
                    report.reason = f"{type(exc).__name__}: {exc}"
                elif good_until == report.size:
                    report.reason = "the file ends without its summary and footer"
                else:
                    report.reason = "the file ends inside a record"
                return
            good_until = source.position
            if isinstance(record, Chunk):
                report.chunks += 1
            for item in contents:
                if isinstance(item, Channel):
                    channels[item.id] = item.topic
                elif isinstance(item, Message):
                    key = channels.get(item.channel_id)
                    if key is None:
                        continue
                    ok = keep.get(item.channel_id)
                    if ok is None:
                        ok = keep[item.channel_id] = wanted is None or wanted(key)
                    if ok:
                        report.messages += 1
                        yield RecordedMessage(key, item.data, item.log_time, item.publish_time, item.sequence)
            if isinstance(record, Footer):
                report.complete = True
                return
