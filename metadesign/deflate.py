"""Parallel deflate: pieces of one zip entry compressed by different workers and joined by concatenation.

A raw deflate stream may be cut anywhere a compressor was flushed with ``Z_SYNC_FLUSH`` (the flush ends
on a byte boundary with an empty stored block and starts no final block): pieces compressed independently,
each ended that way, concatenate into one valid stream, which an empty final block (:data:`FINAL_BLOCK`)
closes.  The entry's CRC32 is combined from the pieces' own (:func:`crc32_combine`, zlib's GF(2) method),
so the assembler never sees the uncompressed bytes: it only concatenates (pigz's scheme, without the
dictionary priming, which costs a little ratio and keeps every piece independent of its neighbours).

:func:`write_zip` writes the container (zip64 where an entry or the central directory needs it, fixed
timestamps: the same entries give the same bytes) for :func:`metadesign.io.write_npz` when an array comes
as :class:`DeflatedArray` pieces."""

from __future__ import annotations

import struct
import zlib
from dataclasses import dataclass
from typing import BinaryIO, Iterable

__all__ = ["crc32_combine", "deflate_piece", "DeflatedArray", "FINAL_BLOCK", "write_zip", "Piece"]

#: an empty final deflate block (fixed Huffman, BFINAL set, end-of-block code): closes a stream of pieces
FINAL_BLOCK = b"\x03\x00"

_CRC_POLY = 0xEDB88320


def _gf2_times(mat: list[int], vec: int) -> int:
    s, i = 0, 0
    while vec:
        if vec & 1:
            s ^= mat[i]
        vec >>= 1
        i += 1
    return s


def _gf2_square(mat: list[int]) -> list[int]:
    return [_gf2_times(mat, mat[n]) for n in range(32)]


def crc32_combine(crc1: int, crc2: int, len2: int) -> int:
    """CRC32 of ``A + B`` from ``crc1 = crc32(A)``, ``crc2 = crc32(B)`` and ``len2 = len(B)`` (zlib's
    ``crc32_combine``: ``crc1`` advanced over ``len2`` zero bytes by squaring the one-zero-bit operator)."""
    if len2 <= 0:
        return crc1
    odd = [_CRC_POLY] + [1 << n for n in range(31)]  # the operator for one zero bit
    even = _gf2_square(odd)  # two zero bits
    odd = _gf2_square(even)  # four
    while True:
        even = _gf2_square(odd)  # eight, sixteen, ... (first pass: one zero byte)
        if len2 & 1:
            crc1 = _gf2_times(even, crc1)
        len2 >>= 1
        if not len2:
            break
        odd = _gf2_square(even)
        if len2 & 1:
            crc1 = _gf2_times(odd, crc1)
        len2 >>= 1
        if not len2:
            break
    return crc1 ^ crc2


@dataclass(frozen=True)
class Piece:
    """A piece of a zip entry: its raw-deflate bytes (sync-flushed), and its uncompressed CRC32 and size."""

    data: bytes
    crc: int
    size: int


def deflate_piece(raw: bytes | memoryview, level: int) -> Piece:
    """``raw`` compressed as a piece of a longer stream (raw deflate, ended by a sync flush)."""
    c = zlib.compressobj(level, zlib.DEFLATED, -15)
    return Piece(c.compress(raw) + c.flush(zlib.Z_SYNC_FLUSH), zlib.crc32(raw), len(raw))


@dataclass(frozen=True)
class DeflatedArray:
    """An array :func:`metadesign.io.write_npz` writes from pieces compressed elsewhere (workers): ``pieces``
    (an iterable of :class:`Piece`, in order) holding the array's C-order bytes; the ``.npy`` header before
    them is made and compressed by the writer."""

    shape: tuple
    dtype: object
    pieces: Iterable[Piece]


# ----------------------------------------------------------------------------------------------------------
# the zip container (PKWARE APPNOTE 6.3: local headers, central directory, zip64 end records)

_DOS_DATE = (0 << 11) | (0 << 5) | 0, ((1980 - 1980) << 9) | (1 << 5) | 1  # 1980-01-01 00:00:00 (time, date)
_U32 = 0xFFFFFFFF


@dataclass
class _Entry:
    name: bytes
    method: int
    crc: int
    csize: int
    usize: int
    offset: int
    zip64: bool


def _local_header(e: _Entry) -> bytes:
    extra = struct.pack("<HHQQ", 1, 16, e.usize, e.csize) if e.zip64 else b""
    return struct.pack("<IHHHHHIIIHH", 0x04034B50, 45 if e.zip64 else 20, 0, e.method, *_DOS_DATE, e.crc,
                       _U32 if e.zip64 else e.csize, _U32 if e.zip64 else e.usize, len(e.name),
                       len(extra)) + e.name + extra


def _central_header(e: _Entry) -> bytes:
    big = e.zip64 or e.offset >= _U32
    extra = struct.pack("<HHQQQ", 1, 24, e.usize, e.csize, e.offset) if big else b""
    return struct.pack("<IHHHHHHIIIHHHHHII", 0x02014B50, (3 << 8) | (45 if big else 20), 45 if big else 20, 0,
                       e.method, *_DOS_DATE, e.crc, _U32 if big else e.csize, _U32 if big else e.usize,
                       len(e.name), len(extra), 0, 0, 0, 0o644 << 16,
                       _U32 if big else e.offset) + e.name + extra


def write_zip(fh: BinaryIO, entries: Iterable[tuple[str, object]], level: int = 6) -> None:
    """Write a zip archive to the seekable ``fh`` from ``entries``: ``(name, bytes)`` (deflated here at
    ``level``) or ``(name, (head, pieces))`` with ``head`` uncompressed bytes and ``pieces`` an iterable
    of :class:`Piece` (concatenated: the bytes never pass through a compressor here).  Entries written from
    pieces always carry zip64 sizes (their size is known only at the end); the central directory takes
    zip64 records when an offset or the entry count needs them."""
    written: list[_Entry] = []
    for name, content in entries:
        nm = name.encode()
        offset = fh.tell()
        if isinstance(content, (bytes, bytearray, memoryview)):
            raw = bytes(content)
            c = zlib.compressobj(level, zlib.DEFLATED, -15)
            data = c.compress(raw) + c.flush()
            e = _Entry(nm, 8, zlib.crc32(raw), len(data), len(raw), offset, len(raw) >= _U32 or len(data) >= _U32)
            fh.write(_local_header(e))
            fh.write(data)
        else:
            head, pieces = content
            e = _Entry(nm, 8, 0, 0, 0, offset, True)
            fh.write(_local_header(e))  # sizes patched below
            first = deflate_piece(head, level)
            crc, usize, csize = first.crc, first.size, len(first.data)
            fh.write(first.data)
            for p in pieces:
                fh.write(p.data)
                crc = crc32_combine(crc, p.crc, p.size)
                usize += p.size
                csize += len(p.data)
            fh.write(FINAL_BLOCK)
            csize += len(FINAL_BLOCK)
            end = fh.tell()
            e.crc, e.usize, e.csize = crc, usize, csize
            fh.seek(offset)
            fh.write(_local_header(e))
            fh.seek(end)
        written.append(e)
    cd_offset = fh.tell()
    for e in written:
        fh.write(_central_header(e))
    cd_size = fh.tell() - cd_offset
    n = len(written)
    if cd_offset >= _U32 or any(e.zip64 or e.offset >= _U32 for e in written) or n >= 0xFFFF:
        z64 = fh.tell()
        fh.write(struct.pack("<IQHHIIQQQQ", 0x06064B50, 44, 45, 45, 0, 0, n, n, cd_size, cd_offset))
        fh.write(struct.pack("<IIQI", 0x07064B50, 0, z64, 1))
        fh.write(struct.pack("<IHHHHIIH", 0x06054B50, 0, 0, min(n, 0xFFFF), min(n, 0xFFFF),
                             min(cd_size, _U32), _U32, 0))
    else:
        fh.write(struct.pack("<IHHHHIIH", 0x06054B50, 0, 0, n, n, cd_size, cd_offset, 0))
