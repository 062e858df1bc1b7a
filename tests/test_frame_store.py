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


def test_points_placed_in_blocks_come_back_as_placed_at_once(tmp_path, monkeypatch):
    """Placing block by block (bounded memory) changes neither the rows nor their order, for
    one array or for frames given one by one, along a bent axis."""
    import pipescan.storage.scratch as scratch
    from pipescan.core.axis import fit_axis
    from pipescan.core.sections import plan_windows

    rng = np.random.default_rng(5)
    s = np.linspace(0.0, 6.0, 60_000)
    theta = rng.uniform(0, 2 * np.pi, s.size)
    # A pipe of 0.5 m that bends by 0.3 m over 6 m, with the wall sampled at random angles.
    bend = 0.3 * (s / 6.0) ** 2
    points = np.column_stack((s, bend + 0.25 * np.cos(theta), 0.25 * np.sin(theta))) + rng.normal(
        scale=0.002, size=(s.size, 3)
    )
    axis = fit_axis(points, start_m=np.zeros(3), travel_m=np.array([6.0, 0.3, 0.0]))
    assert axis.is_curved  # a bent axis: placing does a nearest-node search
    windows = plan_windows(0.0, 6.0, step_m=0.1, window_m=2.0)
    whole = scratch.write_buckets(points, axis, windows, tmp_path / "whole", "chunk_0000000")
    monkeypatch.setattr(scratch, "PLACE_BLOCK_ROWS", 7_000)
    frames = np.array_split(points, 25)  # 2,400 rows each: several frames make a block
    blocked = scratch.write_buckets(iter(frames), axis, windows, tmp_path / "b", "chunk_0000000")
    sliced = scratch.write_buckets(points, axis, windows, tmp_path / "s", "chunk_0000000")
    assert whole == blocked == sliced and whole.points > 0.99 * len(points)
    assert len(list((tmp_path / "b").rglob("*.npy"))) > len(whole.windows_mm)
    for w in windows:
        once = scratch.read_window_rows(tmp_path / "whole", w)
        np.testing.assert_array_equal(scratch.read_window_rows(tmp_path / "b", w), once)
        np.testing.assert_array_equal(scratch.read_window_rows(tmp_path / "s", w), once)


def test_a_windows_rows_come_back_in_file_order_and_a_cut_file_is_refused(tmp_path):
    """A window's files are read into one array in their order, as written; a file cut short
    fails naming it instead of returning fewer rows."""
    import pipescan.storage.scratch as scratch
    from pipescan.core.sections import ChainageWindow

    window = ChainageWindow(0, 2000, 100)
    out = scratch.window_dir(tmp_path, window)
    out.mkdir(parents=True)
    rng = np.random.default_rng(3)
    parts = [rng.random((n, 3)).astype(np.float32) for n in (5, 0, 17, 1)]
    for k, part in enumerate(parts):
        np.save(out / f"chunk_{k:07d}-00000.npy", part)
    rows = scratch.read_window_rows(tmp_path, window)
    assert rows.dtype == np.float32
    np.testing.assert_array_equal(rows, np.concatenate(parts))
    cut = out / "chunk_0000002-00000.npy"
    cut.write_bytes(cut.read_bytes()[:-5])
    with pytest.raises(ValueError, match="chunk_0000002"):
        scratch.read_window_rows(tmp_path, window)
