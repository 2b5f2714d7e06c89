"""Arrays as .npz bytes at a chosen deflate level (numpy's savez_compressed is fixed at zlib's level 6), and chosen
arrays read back from them without opening the archive."""

from __future__ import annotations

import io
import math
import struct
import zipfile
import zlib
from collections.abc import Collection

import numpy as np

NPZ_COMPRESS_LEVEL = 1  # deflate level of prepared frames: level 6 (numpy's) cost 33 ms a frame, 1 costs 8 (+7 %)


def npz_bytes(stored: Collection[str] = (), compress_level: int = NPZ_COMPRESS_LEVEL, **arrays: np.ndarray) -> bytes:
    """Return arrays as .npz bytes (np.load reads them), deflated at `compress_level` except those named in
    `stored`, kept as they are (arrays that deflate barely shrinks cost more time to deflate than they save)."""
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w") as archive:
        for name, value in arrays.items():
            member = io.BytesIO()
            np.lib.format.write_array(member, np.asanyarray(value), allow_pickle=False)
            if name in stored:
                archive.writestr(f"{name}.npy", member.getvalue(), compress_type=zipfile.ZIP_STORED)
            else:
                archive.writestr(f"{name}.npy", member.getvalue(), zipfile.ZIP_DEFLATED, compresslevel=compress_level)
    return buf.getvalue()


# a zip member's local header (APPNOTE 4.3.7): signature, version, flags, method, time, date, CRC-32, compressed and
# uncompressed sizes, name and extra field lengths
_LOCAL_HEADER = struct.Struct("<4s5H3I2H")
_LOCAL_SIGNATURE = b"PK\x03\x04"
_DATA_DESCRIPTOR_FLAG = 0x08  # sizes and CRC after the data, not in the header: left to zipfile


def npz_members(data: bytes, names: Collection[str]) -> dict[str, np.ndarray]:
    """Return the arrays `names` (those present) of .npz bytes, as read-only arrays over `data` (stored members) or
    over their inflated bytes (deflated ones), each checked against its CRC-32 (zipfile.BadZipFile if it fails).

    Reads the members' local headers in order instead of opening the archive: for a prepared frame's image and mask
    zipfile's central directory and member objects cost twice the reading itself (a finish reads every frame back).
    Any layout this does not read (a data descriptor, zip64, another method) is read by zipfile instead.
    """
    found: dict[str, np.ndarray] = {}
    view = memoryview(data)
    pos = 0
    while pos + _LOCAL_HEADER.size <= len(data) and data[pos : pos + 4] == _LOCAL_SIGNATURE:
        _, _, flags, method, _, _, crc, size, full_size, name_len, extra_len = _LOCAL_HEADER.unpack_from(data, pos)
        start = pos + _LOCAL_HEADER.size + name_len + extra_len
        if flags & _DATA_DESCRIPTOR_FLAG or method not in (zipfile.ZIP_STORED, zipfile.ZIP_DEFLATED):
            return _npz_members_by_zipfile(data, names)
        if size == 0xFFFFFFFF or full_size == 0xFFFFFFFF:  # zip64 sizes live in the extra field
            return _npz_members_by_zipfile(data, names)
        name = bytes(view[pos + _LOCAL_HEADER.size : pos + _LOCAL_HEADER.size + name_len]).decode()
        stem = name.removesuffix(".npy")
        if stem in names:
            raw = view[start : start + size]
            body = raw if method == zipfile.ZIP_STORED else memoryview(zlib.decompress(raw, -zlib.MAX_WBITS))
            if zlib.crc32(body) != crc or len(body) != full_size:
                raise zipfile.BadZipFile(f"bad CRC-32 or size for member {name!r}")
            found[stem] = _npy_array(body)
        pos = start + size
    return found


def _npy_array(body: memoryview) -> np.ndarray:
    """Return the array of one .npy member's bytes, read-only over them (no copy: numpy's read_array copies it, 15x
    the time for a frame's image), or as read_array reads it for a header version it reads alone (3.0) and refuses
    it for pickled objects."""
    stream = io.BytesIO(body)
    version = np.lib.format.read_magic(stream)
    headers = {(1, 0): np.lib.format.read_array_header_1_0, (2, 0): np.lib.format.read_array_header_2_0}
    if version not in headers:
        return np.lib.format.read_array(io.BytesIO(body), allow_pickle=False)
    shape, fortran, dtype = headers[version](stream)
    if dtype.hasobject:
        return np.lib.format.read_array(io.BytesIO(body), allow_pickle=False)  # ValueError: no pickles
    array = np.frombuffer(body, dtype, count=math.prod(shape), offset=stream.tell())
    return array.reshape(shape[::-1]).T if fortran else array.reshape(shape)


def _npz_members_by_zipfile(data: bytes, names: Collection[str]) -> dict[str, np.ndarray]:
    """Return the arrays `names` (those present) of .npz bytes read through zipfile (any layout it reads)."""
    with zipfile.ZipFile(io.BytesIO(data)) as archive:
        present = {n.removesuffix(".npy") for n in archive.namelist()}
        return {
            name: np.lib.format.read_array(io.BytesIO(archive.read(f"{name}.npy")), allow_pickle=False)
            for name in names
            if name in present
        }
