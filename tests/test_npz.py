"""Reading .npz archives: the arrays np.load gives, and a damaged archive refused."""

import zipfile

import numpy as np
import pytest

from jaxcomp.npz import read_npz


def _arrays():
    rng = np.random.default_rng(0)
    return {
        "q": rng.standard_normal((1000, 6)),
        "joint": rng.integers(-1, 6, 1000),
        "model": np.array("gen3_lite"),
        "fortran": np.asfortranarray(rng.standard_normal((7, 5))),
        "big_endian": np.arange(5, dtype=">i4"),
        "empty": np.zeros((0, 3)),
        "scalar": np.array(2.5),
        "flags": rng.random(9) > 0.5,
    }


@pytest.mark.parametrize("save", [np.savez, np.savez_compressed])
def test_the_arrays_are_those_numpy_reads(tmp_path, save):
    path = tmp_path / "a.npz"
    save(path, **_arrays())
    got = read_npz(path)
    with np.load(path, allow_pickle=False) as npz:
        want = {k: npz[k] for k in npz.files}
    assert list(got) == list(want)
    for key, value in want.items():
        assert got[key].dtype == value.dtype and got[key].shape == value.shape, key
        assert got[key].flags.f_contiguous == value.flags.f_contiguous, key
        np.testing.assert_array_equal(got[key], value)


def test_a_damaged_or_truncated_archive_is_refused(tmp_path):
    path = tmp_path / "a.npz"
    np.savez(path, **_arrays())
    data = bytearray(path.read_bytes())
    data[data.index(b"\x93NUMPY") + 300] ^= 0xFF  # a byte of the first array's data
    damaged = tmp_path / "damaged.npz"
    damaged.write_bytes(bytes(data))
    with pytest.raises(zipfile.BadZipFile, match="CRC"):
        read_npz(damaged)
    truncated = tmp_path / "truncated.npz"
    truncated.write_bytes(path.read_bytes()[: len(data) // 2])
    with pytest.raises(zipfile.BadZipFile):
        read_npz(truncated)
