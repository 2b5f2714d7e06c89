"""Arrays as .npz bytes (services/core/npz.py): np.load reads them back; stored members are not deflated, the others
at the level asked for."""

from __future__ import annotations

import io
import zipfile

import numpy as np
import pytest

from services.core.npz import NPZ_COMPRESS_LEVEL, npz_bytes, npz_members


def test_arrays_read_back_with_their_members_stored_or_deflated_as_asked() -> None:
    rng = np.random.default_rng(3)
    arrays = {
        "image": rng.integers(0, 256, (48, 64), dtype=np.uint8),
        "counts": np.repeat(np.arange(64, dtype=np.uint16), 40),  # compressible
        "scale": np.float64(8.25),
    }
    data = npz_bytes(stored=("image",), **arrays)
    with np.load(io.BytesIO(data), allow_pickle=False) as z:
        assert sorted(z.files) == ["counts", "image", "scale"]
        for name, value in arrays.items():
            assert z[name].dtype == np.asarray(value).dtype and np.array_equal(z[name], value)
    with zipfile.ZipFile(io.BytesIO(data)) as archive:
        kinds = {info.filename: info.compress_type for info in archive.infolist()}
    assert kinds == {
        "image.npy": zipfile.ZIP_STORED,
        "counts.npy": zipfile.ZIP_DEFLATED,
        "scale.npy": zipfile.ZIP_DEFLATED,
    }


def test_the_deflate_level_is_the_one_asked_for() -> None:
    noisy = np.random.default_rng(4).integers(0, 40, 200_000, dtype=np.uint8)  # level makes a difference here
    fast, small = npz_bytes(compress_level=1, a=noisy), npz_bytes(compress_level=9, a=noisy)
    assert len(small) < len(fast)
    # the default is NPZ_COMPRESS_LEVEL: the same deflated size (whole bytes differ by the members' timestamps)
    assert _member_size(npz_bytes(a=noisy)) == _member_size(npz_bytes(compress_level=NPZ_COMPRESS_LEVEL, a=noisy))
    assert _member_size(fast) != _member_size(small)


def _member_size(data: bytes) -> int:
    """Return the deflated size of an .npz's one member."""
    with zipfile.ZipFile(io.BytesIO(data)) as archive:
        (info,) = archive.infolist()
        return info.compress_size


def _arrays() -> dict[str, np.ndarray]:
    """Return arrays of several dtypes and layouts (a Fortran-ordered one, a scalar, an empty one)."""
    rng = np.random.default_rng(5)
    return {
        "image": rng.integers(0, 256, (48, 64), dtype=np.uint8),
        "mask": np.repeat(np.array([0, 255], np.uint8), 48 * 32).reshape(48, 64),
        "points": np.asfortranarray(rng.normal(size=(7, 2))),
        "scale": np.float64(8.25),
        "none": np.zeros((0, 128), np.float32),
    }


def test_chosen_members_read_back_as_np_load_reads_them_stored_or_deflated() -> None:
    arrays = _arrays()
    for stored in ((), ("image",), tuple(arrays)):
        data = npz_bytes(stored=stored, **arrays)
        got = npz_members(data, ("image", "points", "scale", "none", "absent"))
        assert sorted(got) == ["image", "none", "points", "scale"]  # the absent one is left out, the mask not read
        with np.load(io.BytesIO(data), allow_pickle=False) as z:
            for name, value in got.items():
                assert value.dtype == z[name].dtype and value.shape == z[name].shape
                assert np.array_equal(value, z[name])
        assert not got["image"].flags.writeable  # a view over the file's bytes: nothing writes into it


def test_a_damaged_member_is_refused_by_its_crc() -> None:
    data = bytearray(npz_bytes(stored=("image",), **_arrays()))
    start = bytes(data).index(b"image.npy") + len("image.npy") + 200  # past the local header, into the array
    data[start] ^= 0xFF
    with pytest.raises(zipfile.BadZipFile, match=r"image\.npy"):
        npz_members(bytes(data), ("image",))
    assert np.array_equal(npz_members(bytes(data), ("mask",))["mask"], _arrays()["mask"])  # another member reads


def test_an_archive_written_with_data_descriptors_is_read_through_zipfile() -> None:
    class Unseekable(io.RawIOBase):
        """A write-only stream zipfile cannot seek back into: it writes data descriptors after each member."""

        def __init__(self) -> None:
            self.chunks: list[bytes] = []

        def writable(self) -> bool:
            return True

        def write(self, b: bytes) -> int:  # type: ignore[override]
            self.chunks.append(bytes(b))
            return len(b)

    stream = Unseekable()
    with zipfile.ZipFile(stream, "w") as archive:
        member = io.BytesIO()
        np.lib.format.write_array(member, _arrays()["image"])
        archive.writestr("image.npy", member.getvalue(), zipfile.ZIP_DEFLATED)
    data = b"".join(stream.chunks)
    assert zipfile.ZipFile(io.BytesIO(data)).infolist()[0].flag_bits & 0x08  # the layout the fast path leaves
    assert np.array_equal(npz_members(data, ("image",))["image"], _arrays()["image"])


def test_a_member_with_a_version_3_header_or_pickled_objects_is_read_as_numpy_reads_it() -> None:
    member = io.BytesIO()
    np.lib.format.write_array(member, _arrays()["points"], version=(3, 0))
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w") as archive:
        archive.writestr("points.npy", member.getvalue(), zipfile.ZIP_STORED)
    assert np.array_equal(npz_members(buf.getvalue(), ("points",))["points"], _arrays()["points"])
    objects = io.BytesIO()
    np.lib.format.write_array(objects, np.array([{"a": 1}], dtype=object), allow_pickle=True)
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w") as archive:
        archive.writestr("objects.npy", objects.getvalue(), zipfile.ZIP_STORED)
    with pytest.raises(ValueError, match="allow_pickle"):
        npz_members(buf.getvalue(), ("objects",))
