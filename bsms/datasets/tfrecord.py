"""TFRecord framing, read as a stream with every checksum verified.

A TFRecord file is a sequence of records, each ``uint64 length``, ``uint32 masked CRC32C of
the length bytes``, ``length`` bytes of data, ``uint32 masked CRC32C of the data`` (all
little-endian; mask: ``((crc >> 15) | (crc << 17)) + 0xa282ead8`` mod 2^32). Records are read
one at a time, so memory stays constant whatever the file size; a truncated file, a length or
data checksum that does not match, or trailing bytes raise :class:`SourceError` naming the
file and the record.
"""

from __future__ import annotations

import struct
from collections.abc import Iterator
from pathlib import Path

import crc32c

from bsms.datasets.errors import SourceError

__all__ = ["masked_crc", "read_records", "frame_record"]

_MASK_DELTA = 0xA282EAD8


def masked_crc(data: bytes) -> int:
    """TFRecord's masked CRC32C of ``data``."""
    crc = crc32c.crc32c(data)
    return (((crc >> 15) | (crc << 17)) + _MASK_DELTA) & 0xFFFFFFFF


def frame_record(data: bytes) -> bytes:
    """``data`` framed as one TFRecord record (what a TFRecord writer appends)."""
    length = struct.pack("<Q", len(data))
    return length + struct.pack("<I", masked_crc(length)) + data + struct.pack("<I", masked_crc(data))


def _read_exact(handle, size: int, path: Path, index: int, what: str) -> bytes:
    data = handle.read(size)
    if len(data) != size:
        raise SourceError(path, f"the file ends inside the record ({what}: {len(data)} of {size} bytes); it is "
                                "truncated: download it again", record=index)
    return data


def read_records(path) -> Iterator[bytes]:
    """Each record's data bytes in order, after checking both checksums."""
    path = Path(path)
    if not path.is_file():
        raise SourceError(path, "the file does not exist")
    with open(path, "rb") as handle:
        index = 0
        while True:
            head = handle.read(8)
            if not head:
                return
            if len(head) != 8:
                raise SourceError(path, f"the file ends inside a record's length ({len(head)} of 8 bytes); it is "
                                        "truncated: download it again", record=index)
            (stored,) = struct.unpack("<I", _read_exact(handle, 4, path, index, "length checksum"))
            if stored != masked_crc(head):
                raise SourceError(path, "the length checksum does not match (CRC32C): the file is corrupt or not "
                                        "a TFRecord file; download it again", record=index)
            (length,) = struct.unpack("<Q", head)
            data = _read_exact(handle, length, path, index, "data")
            (stored,) = struct.unpack("<I", _read_exact(handle, 4, path, index, "data checksum"))
            if stored != masked_crc(data):
                raise SourceError(path, "the data checksum does not match (CRC32C): the record is corrupt; "
                                        "download the file again", record=index)
            yield data
            index += 1
