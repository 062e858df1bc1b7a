"""The one .npy header reader: the same answer as NumPy's, for every header version, and the
data left where the array starts. (The race it guards against, CPython gh-106905, shows only
under load on CPython < 3.11.8, so it is documented rather than reproduced here.)"""

from __future__ import annotations

import io

import numpy as np
import pytest

from pipescan.core.npyheader import read_npy_header


@pytest.mark.parametrize("version", [(1, 0), (2, 0), (3, 0)])
@pytest.mark.parametrize("fortran", [False, True])
def test_header_matches_numpy_and_leaves_the_data_next(version, fortran) -> None:
    arr = np.arange(12, dtype=np.float32).reshape(4, 3)
    arr = np.asfortranarray(arr) if fortran else arr
    buf = io.BytesIO()
    np.lib.format.write_array(buf, arr, version=version)
    buf.seek(0)
    shape, is_fortran, dtype = read_npy_header(buf)
    assert (shape, is_fortran, dtype) == ((4, 3), fortran, np.dtype(np.float32))
    data = np.frombuffer(buf.read(), dtype=dtype).reshape(shape, order="F" if fortran else "C")
    np.testing.assert_array_equal(data, arr)


def test_not_a_npy_file_is_a_value_error() -> None:
    with pytest.raises(ValueError):
        read_npy_header(io.BytesIO(b"not an npy file at all"))
