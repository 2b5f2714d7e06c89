"""Arrays as .npz bytes (services/core/npz.py): np.load reads them back; stored members are not deflated, the others
at the level asked for."""

from __future__ import annotations

import io
import zipfile

import numpy as np

from services.core.npz import NPZ_COMPRESS_LEVEL, npz_bytes


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
