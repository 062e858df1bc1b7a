"""Point files: round trips in every format, and a clear error for every kind of bad file."""

from __future__ import annotations

import tempfile
from pathlib import Path

import laspy
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from pipescan.core.errors import PointFileError
from pipescan.storage.input.pointfiles import (
    LAS_SCALE_M,
    MM_HINT,
    POINT_SUFFIXES,
    check_point_file,
    is_point_file,
    read_points,
    write_points,
)
from pipescan.storage.input.readers import FORMATS, READERS

ARCHIVE = "run-0042.zip"


def cylinder_frame(n: int = 400, *, diameter_m: float = 0.5, seed: int = 0) -> np.ndarray:
    """(n, 3) points on a pipe wall in sensor coordinates: axis along x through the sensor,
    0.5 to 3 m ahead (the sensor's blind zone is 0.5 m)."""
    rng = np.random.default_rng(seed)
    angle = rng.uniform(0.0, 2.0 * np.pi, n)
    radius = diameter_m / 2.0 + rng.normal(0.0, 0.002, n)
    return np.column_stack(
        [rng.uniform(0.5, 3.0, n), radius * np.cos(angle), radius * np.sin(angle)]
    )


def read_in_archive(path: Path, **kwargs) -> np.ndarray:
    return read_points(path, archive=ARCHIVE, member=f"frames/{path.name}", **kwargs)


def assert_names_place(err: PointFileError, path: Path, field: str) -> None:
    """The error and its message name the archive, the member file and the field."""
    member = f"frames/{path.name}"
    assert err.archive == ARCHIVE
    assert err.file == member
    assert err.field == field
    text = str(err)
    assert ARCHIVE in text
    assert member in text
    assert repr(field) in text
    assert err.hint


# --- round trips ------------------------------------------------------------------------------


@pytest.mark.parametrize("suffix", POINT_SUFFIXES)
def test_round_trip_every_format(tmp_path: Path, suffix: str) -> None:
    points = cylinder_frame()
    path = tmp_path / f"frame{suffix}"
    write_points(path, points)
    back = read_points(path)
    assert back.shape == points.shape
    assert back.dtype == np.float64
    # LAS/LAZ store a 0.1 mm integer grid (error <= half a step); PCD is float32.
    assert np.abs(back - points).max() <= 1e-4


@pytest.mark.parametrize("suffix", [".las", ".laz"])
def test_las_scale_and_offset(tmp_path: Path, suffix: str) -> None:
    points = cylinder_frame() + np.array([512_000.0, 6_170_000.0, 12.0])  # georeferenced
    path = tmp_path / f"cloud{suffix}"
    write_points(path, points)
    header = laspy.read(path).header
    np.testing.assert_allclose(header.scales, LAS_SCALE_M)
    np.testing.assert_allclose(header.offsets, points.min(axis=0))
    back = read_points(path, kind="cloud")
    assert np.abs(back - points).max() <= LAS_SCALE_M / 2 + 1e-9


def test_laz_is_compressed(tmp_path: Path) -> None:
    points = cylinder_frame(5000)
    write_points(tmp_path / "a.las", points)
    write_points(tmp_path / "a.laz", points)
    las_bytes = (tmp_path / "a.las").stat().st_size
    laz_bytes = (tmp_path / "a.laz").stat().st_size
    assert laz_bytes < 0.6 * las_bytes
    np.testing.assert_array_equal(read_points(tmp_path / "a.laz"), read_points(tmp_path / "a.las"))


def test_ascii_with_header_comments_and_extra_columns(tmp_path: Path) -> None:
    points = cylinder_frame(50)
    intensity = np.arange(50)
    rows = [
        f"{x!r} {y!r} {z!r} {i} 7" for (x, y, z), i in zip(points.tolist(), intensity, strict=True)
    ]
    text = "# exported by scanner v2\n//x y z intensity ring\nX Y Z Intensity Ring\n"
    text += "\n".join(rows[:25]) + "\n# a comment mid-file\n\n" + "\n".join(rows[25:]) + "\n"
    path = tmp_path / "frame.txt"
    path.write_text(text)
    np.testing.assert_array_equal(read_points(path), points)

    csv = tmp_path / "frame.xyz"
    csv.write_text(
        "x,y,z,intensity\n" + "\n".join(",".join(map(repr, p)) + ",1" for p in points.tolist())
    )
    np.testing.assert_array_equal(read_points(csv), points)


# Coordinates within 25 m per axis keep the median range under the 50 m millimetre test.
_coords = st.floats(-25.0, 25.0, allow_nan=False, allow_infinity=False, width=64)


@settings(max_examples=60, deadline=None)
@given(
    points=st.integers(1, 40).flatmap(lambda n: arrays(np.float64, (n, 3), elements=_coords)),
    delimiter=st.sampled_from([" ", ",", "\t", ", ", "  "]),
    header=st.booleans(),
    extra_columns=st.integers(0, 3),
)
def test_ascii_round_trip_property(
    points: np.ndarray, delimiter: str, header: bool, extra_columns: int
) -> None:
    """Whatever the separator, header and extra columns, x y z come back exactly."""
    lines = ["x y z" + " extra" * extra_columns] if header else []
    lines += [delimiter.join([repr(float(v)) for v in p] + ["1.5"] * extra_columns) for p in points]
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "frame.xyz"
        path.write_text("\n".join(lines) + "\n")
        np.testing.assert_array_equal(read_points(path), points)
        write_points(path, points)  # and the writer is lossless
        np.testing.assert_array_equal(read_points(path), points)


def test_npy_accepts_any_float_dtype(tmp_path: Path) -> None:
    points = cylinder_frame().astype(np.float32)
    np.save(tmp_path / "f.npy", points)
    back = read_points(tmp_path / "f.npy")
    assert back.dtype == np.float64
    np.testing.assert_array_equal(back, points.astype(np.float64))


def test_georeferenced_cloud_in_metres_passes_but_not_as_a_frame(tmp_path: Path) -> None:
    cloud = cylinder_frame(2000, diameter_m=3.0) + np.array([512_000.0, 6_170_000.0, 40.0])
    path = tmp_path / "cloud.npy"
    write_points(path, cloud)
    np.testing.assert_array_equal(read_points(path, kind="cloud"), cloud)
    with pytest.raises(PointFileError, match="millimetres"):
        read_points(path, kind="frame")


# --- errors -----------------------------------------------------------------------------------


def _truncate(path: Path, keep_ratio: float = 0.5) -> None:
    data = path.read_bytes()
    path.write_bytes(data[: int(len(data) * keep_ratio)])


@pytest.mark.parametrize("suffix", [".las", ".laz", ".ply", ".pcd", ".npy", ".xyz"])
def test_truncated_file(tmp_path: Path, suffix: str) -> None:
    path = tmp_path / f"000003{suffix}"
    write_points(path, cylinder_frame())
    _truncate(path)
    with pytest.raises(PointFileError) as info:
        read_in_archive(path)
    assert_names_place(info.value, path, "points")


def test_truncated_las_header(tmp_path: Path) -> None:
    path = tmp_path / "000001.las"
    write_points(path, cylinder_frame())
    _truncate(path, 0.01)
    with pytest.raises(PointFileError, match="cannot read LAS") as info:
        read_in_archive(path)
    assert_names_place(info.value, path, "points")


def test_truncated_ascii_ply_and_pcd(tmp_path: Path) -> None:
    """Open3D fills a truncated ASCII cloud with garbage rather than failing: we must not."""
    import open3d as o3d

    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(cylinder_frame()))
    for suffix in (".ply", ".pcd"):
        path = tmp_path / f"ascii{suffix}"
        o3d.io.write_point_cloud(str(path), cloud, write_ascii=True)
        _truncate(path)
        with pytest.raises(PointFileError, match="truncated") as info:
            read_in_archive(path)
        assert_names_place(info.value, path, "points")


def test_garbage_ply(tmp_path: Path) -> None:
    rng = np.random.default_rng(7)
    garbage = tmp_path / "garbage.ply"
    garbage.write_bytes(rng.integers(0, 256, 4000, dtype=np.uint8).tobytes())
    with pytest.raises(PointFileError, match="not a PLY file") as info:
        read_in_archive(garbage)
    assert_names_place(info.value, garbage, "points")

    # A valid header followed by random bytes, too few for the declared vertices.
    header = (
        b"ply\nformat binary_little_endian 1.0\nelement vertex 400\n"
        b"property double x\nproperty double y\nproperty double z\nend_header\n"
    )
    short = tmp_path / "short.ply"
    short.write_bytes(header + rng.integers(0, 256, 1000, dtype=np.uint8).tobytes())
    with pytest.raises(PointFileError, match="truncated") as info:
        read_in_archive(short)
    assert_names_place(info.value, short, "points")

    # The right number of random bytes: the values are absurd, and that is caught too.
    full = tmp_path / "full.ply"
    full.write_bytes(header + rng.integers(0, 256, 400 * 24, dtype=np.uint8).tobytes())
    with pytest.raises(PointFileError) as info:
        read_in_archive(full)
    assert info.value.file == "frames/full.ply"


def test_ply_without_z(tmp_path: Path) -> None:
    path = tmp_path / "xy.ply"
    xy = cylinder_frame()[:, :2]
    path.write_bytes(
        b"ply\nformat binary_little_endian 1.0\nelement vertex 400\n"
        b"property double x\nproperty double y\nend_header\n" + xy.astype("<f8").tobytes()
    )
    with pytest.raises(PointFileError, match="no 'z' property") as info:
        read_in_archive(path)
    assert_names_place(info.value, path, "z")


def test_npy_wrong_shape(tmp_path: Path) -> None:
    path = tmp_path / "flat.npy"
    np.save(path, cylinder_frame()[:, :2])
    with pytest.raises(PointFileError, match=r"shape \(400, 2\); expected \(N, 3\)") as info:
        read_in_archive(path)
    assert_names_place(info.value, path, "points")


def test_npy_integer_dtype(tmp_path: Path) -> None:
    path = tmp_path / "int.npy"
    np.save(path, (cylinder_frame() * 1000).astype(np.int32))
    with pytest.raises(PointFileError, match="dtype int32") as info:
        read_in_archive(path)
    assert_names_place(info.value, path, "points")


def test_npy_pickled_object_array_is_refused(tmp_path: Path) -> None:
    path = tmp_path / "obj.npy"
    np.save(path, np.array([{"x": 1}], dtype=object), allow_pickle=True)
    # Refused on its header's dtype, before anything could be unpickled.
    with pytest.raises(PointFileError, match=r"dtype object") as info:
        read_in_archive(path)
    assert_names_place(info.value, path, "points")


@pytest.mark.parametrize("suffix", POINT_SUFFIXES)
def test_empty_frame(tmp_path: Path, suffix: str) -> None:
    path = tmp_path / f"empty{suffix}"
    write_points(path, np.empty((0, 3)))
    with pytest.raises(PointFileError, match="empty frame") as info:
        read_in_archive(path)
    assert_names_place(info.value, path, "points")


def test_header_only_ascii_is_empty(tmp_path: Path) -> None:
    path = tmp_path / "header.xyz"
    path.write_text("x y z\n# nothing captured\n")
    with pytest.raises(PointFileError, match="empty frame") as info:
        read_in_archive(path)
    assert_names_place(info.value, path, "points")


@pytest.mark.parametrize("suffix", [".npy", ".xyz", ".ply", ".pcd"])
def test_nan_and_inf_are_counted(tmp_path: Path, suffix: str) -> None:
    points = cylinder_frame()
    points[[3, 50, 51], 0] = np.nan
    points[200, 2] = np.inf
    path = tmp_path / f"nan{suffix}"
    write_points(path, points)
    with pytest.raises(PointFileError, match=r"4 of 400 points have NaN or infinite") as info:
        read_in_archive(path)
    assert_names_place(info.value, path, "x,z")
    assert "x: 3, y: 0, z: 1" in str(info.value)


@pytest.mark.parametrize("suffix", [".las", ".laz", ".npy", ".xyz", ".ply"])
def test_millimetre_frame(tmp_path: Path, suffix: str) -> None:
    path = tmp_path / f"mm{suffix}"
    write_points(path, cylinder_frame() * 1000.0)
    with pytest.raises(PointFileError) as info:
        read_in_archive(path)
    assert_names_place(info.value, path, "points")
    assert MM_HINT in str(info.value)


def test_millimetre_cloud(tmp_path: Path) -> None:
    cloud_m = cylinder_frame(2000, diameter_m=0.5) + np.array([512_000.0, 6_170_000.0, 40.0])
    path = tmp_path / "cloud.las"
    write_points(path, cloud_m * 1000.0)
    with pytest.raises(PointFileError) as info:
        read_in_archive(path, kind="cloud")
    assert_names_place(info.value, path, "points")
    assert MM_HINT in str(info.value)


def test_large_pipe_in_metres_is_not_millimetres(tmp_path: Path) -> None:
    path = tmp_path / "big.npy"
    write_points(path, cylinder_frame(diameter_m=5.0) * np.array([10.0, 1.0, 1.0]))
    assert read_in_archive(path).shape == (400, 3)
    assert read_in_archive(path, kind="cloud").shape == (400, 3)


def test_unknown_suffix_and_missing_file(tmp_path: Path) -> None:
    path = tmp_path / "scan.fls"
    path.write_bytes(b"\0" * 16)
    with pytest.raises(PointFileError, match=r"unsupported point-file suffix '\.fls'") as info:
        read_in_archive(path)
    assert_names_place(info.value, path, "points")
    with pytest.raises(PointFileError, match="does not exist"):
        read_in_archive(tmp_path / "gone.npy")


def test_ascii_short_and_bad_rows(tmp_path: Path) -> None:
    short = tmp_path / "short.xyz"
    short.write_text("1 2 3\n4 5\n")
    with pytest.raises(PointFileError, match="cannot read x y z rows") as info:
        read_in_archive(short)
    assert_names_place(info.value, short, "points")
    bad = tmp_path / "bad.xyz"
    bad.write_text("1 2 3\n4 five 6\n")
    with pytest.raises(PointFileError, match="five"):
        read_in_archive(bad)
    binary = tmp_path / "binary.txt"
    binary.write_bytes(b"\xff\xfe\x00garbage\x81")
    with pytest.raises(PointFileError, match="cannot read ASCII points"):
        read_in_archive(binary)


def test_write_points_rejects_bad_input(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match=r"shape \(N, 3\)"):
        write_points(tmp_path / "a.npy", np.zeros((4, 2)))
    with pytest.raises(ValueError, match="suffix"):
        write_points(tmp_path / "a.fls", np.zeros((4, 3)))
    with pytest.raises(ValueError, match="NaN"):
        write_points(tmp_path / "a.las", np.full((4, 3), np.nan))


# --- the reader registry ------------------------------------------------------------------------


@pytest.mark.parametrize("fmt", FORMATS, ids=[f.name for f in FORMATS])
def test_every_reader_checks_what_it_reads(tmp_path: Path, fmt) -> None:
    """``check`` tells the count ``read`` returns, for every registered format, and a file cut
    short fails both (ASCII declares no count: its check counts fewer rows instead)."""
    for suffix in fmt.suffixes:
        path = tmp_path / f"frame{suffix}"
        points = cylinder_frame(2345, seed=3)
        write_points(path, points)
        assert check_point_file(path) == len(read_points(path)) == 2345
        _truncate(path, 0.6)
        if fmt.name == "ASCII x y z":
            assert check_point_file(path) < 2345
            continue
        with pytest.raises(PointFileError):
            check_point_file(path)
        with pytest.raises(PointFileError):
            read_points(path)


def test_registry_keys_are_the_point_suffixes() -> None:
    assert set(POINT_SUFFIXES) == set(READERS)
    assert all(s == s.lower() and s.startswith(".") for s in READERS)


def test_an_unknown_suffix_is_never_read_as_text(tmp_path: Path) -> None:
    path = tmp_path / "frame.fls"
    path.write_text("1 2 3\n4 5 6\n")
    with pytest.raises(PointFileError, match=r"unsupported point-file suffix '\.fls'"):
        read_points(path)
    assert not is_point_file(path)
