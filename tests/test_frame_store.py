"""The run's frame store: frames written once by registration, read back by the sections."""

from __future__ import annotations

import numpy as np
import pytest

from pipescan.storage.scratch import FrameStore


def _frames(rng, count):
    return [(10 + k, rng.normal(size=(int(rng.integers(0, 500)), 3))) for k in range(count)]


def test_frames_come_back_in_order_as_float32(tmp_path):
    rng = np.random.default_rng(3)
    store = FrameStore(tmp_path / "frames")
    frames = _frames(rng, 7)
    with store.writer(10) as w:
        for i, pts in frames:
            w.add(i, pts)
    back = list(store.iter_frames(10))
    assert [i for i, _ in back] == [i for i, _ in frames]
    for (_, got), (_, sent) in zip(back, frames, strict=True):
        assert got.dtype == np.float32 and got.shape == sent.shape
        np.testing.assert_array_equal(got, sent.astype(np.float32))
    some = [i for i, _ in store.iter_frames(10, [16, 12, 99])]
    assert some == [12, 16]


def test_a_chunk_that_failed_leaves_no_file(tmp_path):
    store = FrameStore(tmp_path / "frames")
    with pytest.raises(RuntimeError), store.writer(0) as w:
        w.add(0, np.ones((5, 3)))
        raise RuntimeError("registration failed")
    assert not store.has_chunk(0)
    assert list((tmp_path / "frames").iterdir()) == []
