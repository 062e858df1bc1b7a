"""Scan archives: every container, the layout rules, safe extraction and clear errors."""

from __future__ import annotations

import io
import math
import shutil
import stat
import tarfile
import zipfile
from datetime import UTC, datetime
from pathlib import Path

import fsspec
import numpy as np
import pytest

from pipescan.core.errors import ArchiveError, MetadataError, PointFileError
from pipescan.storage.input.archive import natural_key, open_archive, validate_archive
from pipescan.storage.input.metadata import parse_inspection_toml
from pipescan.storage.input.pointfiles import write_points

TOML = """\
asset_id = "MH1042-MH1043"
inspected_at = 2024-05-17T09:30:00
nominal_diameter_m = 0.5
upstream_node = "MH1042"
downstream_node = "MH1043"
chainage_offset_m = 1.25
survey_crew = "B"   # unknown keys are ignored
"""


def cylinder_frame(n: int = 300, *, seed: int = 0) -> np.ndarray:
    """(n, 3) points on a 0.5 m pipe wall in sensor coordinates (axis along x)."""
    rng = np.random.default_rng(seed)
    angle = rng.uniform(0.0, 2.0 * np.pi, n)
    return np.column_stack([rng.uniform(0.5, 3.0, n), 0.25 * np.cos(angle), 0.25 * np.sin(angle)])


def make_frames_dir(
    root: Path, names=("f1.npy", "f2.npy", "f10.npy"), toml: str = TOML
) -> dict[str, np.ndarray]:
    """Write an archive directory with one frame per name; return the points by member."""
    root.mkdir(parents=True, exist_ok=True)
    (root / "inspection.toml").write_text(toml)
    frames = {}
    for seed, name in enumerate(names):
        points = cylinder_frame(seed=seed)
        write_points(root / "frames" / name, points)
        frames[f"frames/{name}"] = points
    return frames


def zip_dir(src: Path, dst: Path, prefix: str = "") -> Path:
    with zipfile.ZipFile(dst, "w", zipfile.ZIP_DEFLATED) as zf:
        for path in sorted(src.rglob("*")):
            if path.is_file():
                zf.write(path, prefix + path.relative_to(src).as_posix())
    return dst


def tar_dir(src: Path, dst: Path, mode: str = "w", prefix: str = "") -> Path:
    with tarfile.open(dst, mode) as tf:
        for path in sorted(src.rglob("*")):
            tf.add(path, prefix + path.relative_to(src).as_posix(), recursive=False)
    return dst


def assert_names(err: Exception, archive: str, file: str, field: str) -> None:
    assert err.archive == archive
    assert err.file == file
    assert err.field == field
    text = str(err)
    assert f"archive {archive}" in text
    assert f"file {file}" in text
    assert f"field {field!r}" in text


# --- containers -------------------------------------------------------------------------------


def test_directory_archive(tmp_path: Path) -> None:
    frames = make_frames_dir(tmp_path / "run")
    with open_archive(tmp_path / "run") as arc:
        assert arc.name == str(tmp_path / "run")
        assert arc.root == tmp_path / "run"
        assert arc.has_frames
        assert arc.cloud_member is None
        meta = arc.meta
        assert meta.asset_id == "MH1042-MH1043"
        assert meta.inspected_at == datetime(2024, 5, 17, 9, 30)
        assert meta.nominal_diameter_m == 0.5
        assert (meta.upstream_node, meta.downstream_node) == ("MH1042", "MH1043")
        assert meta.chainage_offset_m == 1.25
        assert meta.direction == "downstream"
        # Natural order: f2 before f10.
        assert [f.file for f in meta.frames] == ["frames/f1.npy", "frames/f2.npy", "frames/f10.npy"]
        assert all(f.time_s is None and f.odometer_m is None for f in meta.frames)
        for i, points in arc.iter_frames():
            np.testing.assert_array_equal(points, frames[meta.frames[i].file])
    assert (tmp_path / "run" / "frames" / "f1.npy").exists()  # a directory is never removed


@pytest.mark.parametrize(
    "pack",
    [
        lambda src, dst: zip_dir(src, dst / "run.zip"),
        lambda src, dst: tar_dir(src, dst / "run.tar"),
        lambda src, dst: tar_dir(src, dst / "run.tar.gz", "w:gz"),
        lambda src, dst: tar_dir(src, dst / "run.tgz", "w:gz"),
        lambda src, dst: zip_dir(src, dst / "run.zip", prefix="MH1042-MH1043/"),
        lambda src, dst: tar_dir(src, dst / "run.tar.gz", "w:gz", prefix="MH1042-MH1043/"),
    ],
    ids=["zip", "tar", "tar.gz", "tgz", "folder-in-zip", "folder-in-tar.gz"],
)
def test_file_archives(tmp_path: Path, pack) -> None:
    frames = make_frames_dir(tmp_path / "src")
    packed = pack(tmp_path / "src", tmp_path)
    work = tmp_path / "work"
    with open_archive(str(packed), workdir=work) as arc:
        assert arc.name == str(packed)
        assert arc.root.is_relative_to(work)
        assert [f.file for f in arc.meta.frames] == list(frames)
        for i, points in arc.iter_frames():
            np.testing.assert_array_equal(points, frames[arc.meta.frames[i].file])
        assert len(list(work.iterdir())) == 1
    assert list(work.iterdir()) == []  # the extraction is removed on close


def test_memory_url(tmp_path: Path) -> None:
    frames = make_frames_dir(tmp_path / "src")
    data = zip_dir(tmp_path / "src", tmp_path / "run.zip").read_bytes()
    fs = fsspec.filesystem("memory")
    url = "memory://pipescan-test/MH1042-MH1043.zip"
    with fs.open(url, "wb") as fh:
        fh.write(data)
    try:
        with open_archive(url, workdir=tmp_path / "work") as arc:
            assert arc.name == url
            np.testing.assert_array_equal(arc.read_frame(2), frames["frames/f10.npy"])
        with pytest.raises(ArchiveError, match="does not exist"):
            open_archive("memory://pipescan-test/missing.zip", workdir=tmp_path / "work")
        assert list((tmp_path / "work").iterdir()) == []
    finally:
        fs.rm("memory://pipescan-test", recursive=True)


def test_file_url(tmp_path: Path) -> None:
    make_frames_dir(tmp_path / "src")
    packed = zip_dir(tmp_path / "src", tmp_path / "run.zip")
    with open_archive(packed.as_uri()) as arc:
        assert arc.frame_count == 3


def test_frames_table_sets_order_and_times(tmp_path: Path) -> None:
    toml = TOML + "".join(
        f'[[frames]]\nfile = "{name}"\ntime_s = {t}\nodometer_m = {o}\n'
        for name, t, o in [
            ("frames/f10.npy", 0.0, 0.0),
            ("f2.npy", 0.1, 0.012),
            ("frames/f1.npy", 0.2, 0.03),
        ]
    )
    frames = make_frames_dir(tmp_path / "run", toml=toml)
    with open_archive(tmp_path / "run") as arc:
        refs = arc.meta.frames
        # "f2.npy" is resolved into frames/.
        assert [f.file for f in refs] == ["frames/f10.npy", "frames/f2.npy", "frames/f1.npy"]
        assert [f.time_s for f in refs] == [0.0, 0.1, 0.2]
        assert [f.odometer_m for f in refs] == [0.0, 0.012, 0.03]
        np.testing.assert_array_equal(arc.read_frame(0), frames["frames/f10.npy"])
        assert [i for i, _ in arc.iter_frames([2, 0])] == [2, 0]
        with pytest.raises(IndexError):
            arc.read_frame(3)


def test_natural_key() -> None:
    names = ["frame10.las", "frame2.las", "Frame1.las", "frame2b.las", "frame100.las"]
    assert sorted(names, key=natural_key) == [
        "Frame1.las",
        "frame2.las",
        "frame2b.las",
        "frame10.las",
        "frame100.las",
    ]


def test_mixed_formats_and_junk_are_handled(tmp_path: Path) -> None:
    root = tmp_path / "run"
    make_frames_dir(root, names=("000001.las", "000002.ply", "000003.npy"))
    (root / "frames" / "._000001.las").write_bytes(b"macOS resource fork")
    (root / "frames" / "notes.md").write_text("ignored")
    (root / "README.md").write_text("ignored")
    with open_archive(root) as arc:
        assert [f.file for f in arc.meta.frames] == [
            "frames/000001.las",
            "frames/000002.ply",
            "frames/000003.npy",
        ]
        assert validate_archive(arc).point_count == 900


def test_content_hash(tmp_path: Path) -> None:
    make_frames_dir(tmp_path / "run")
    packed = zip_dir(tmp_path / "run", tmp_path / "run.zip")
    with open_archive(tmp_path / "run") as a, open_archive(tmp_path / "run") as b:
        assert a.content_hash == b.content_hash
        assert len(a.content_hash) == 64
        dir_hash = a.content_hash
    with open_archive(packed) as a, open_archive(packed) as b:
        assert a.content_hash == b.content_hash
        assert a.content_hash == dir_hash  # by design; the contract only needs the line above
    # One coordinate changes: the hash changes. An ignored file does not change it.
    (tmp_path / "run" / "notes.txt.bak").write_text("ignored")
    with open_archive(tmp_path / "run") as arc:
        assert arc.content_hash == dir_hash
    write_points(tmp_path / "run" / "frames" / "f2.npy", cylinder_frame(seed=1) + 1e-3)
    with open_archive(tmp_path / "run") as arc:
        assert arc.content_hash != dir_hash


@pytest.mark.parametrize("name", ["cloud.las", "cloud.laz", "cloud.ply", "registered.npy"])
def test_cloud_archive(tmp_path: Path, name: str) -> None:
    root = tmp_path / "run"
    root.mkdir()
    (root / "inspection.toml").write_text(TOML)
    cloud = cylinder_frame(2000) + np.array([512_000.0, 6_170_000.0, 40.0])
    write_points(root / name, cloud)
    with open_archive(root) as arc:
        assert not arc.has_frames
        assert arc.cloud_member == name
        assert arc.meta.frames == ()
        assert np.abs(arc.read_cloud() - cloud).max() <= 1e-4
        with pytest.raises(ArchiveError, match="holds a registered cloud, not frames"):
            arc.read_frame(0)
        assert validate_archive(arc).point_count == 2000


def test_reading_after_close_fails(tmp_path: Path) -> None:
    make_frames_dir(tmp_path / "run")
    arc = open_archive(zip_dir(tmp_path / "run", tmp_path / "run.zip"), workdir=tmp_path / "w")
    root = arc.root
    arc.close()
    arc.close()
    assert not root.exists()
    with pytest.raises(ArchiveError, match="closed"):
        arc.read_frame(0)


# --- content problems surface when read, and in validate_archive ------------------------------


def test_nan_frame_is_caught_by_validate_archive(tmp_path: Path) -> None:
    root = tmp_path / "run"
    make_frames_dir(root, names=("f1.npy", "f2.npy", "f3.npy"))
    bad = cylinder_frame(seed=9)
    bad[17, 1] = np.nan
    write_points(root / "frames" / "f3.npy", bad)
    packed = str(zip_dir(root, tmp_path / "run.zip"))
    with open_archive(packed) as arc:  # streaming: opening does not read the frames
        np.testing.assert_array_equal(arc.read_frame(0), cylinder_frame(seed=0))
        with pytest.raises(PointFileError, match="1 of 300 points have NaN") as info:
            validate_archive(arc)
        assert_names(info.value, packed, "frames/f3.npy", "y")
        # Without point checks it passes: only the structure is checked.
        assert validate_archive(arc, check_points=False).frame_count == 3


def test_millimetre_frame_is_caught_by_validate_archive(tmp_path: Path) -> None:
    root = tmp_path / "run"
    make_frames_dir(root, names=("f1.las", "f2.las"))
    write_points(root / "frames" / "f2.las", cylinder_frame() * 1000.0)
    with open_archive(root) as arc, pytest.raises(PointFileError, match="divide by 1000") as info:
        validate_archive(arc)
    assert_names(info.value, str(root), "frames/f2.las", "points")


# --- metadata errors --------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("toml", "field", "message"),
    [
        (TOML.replace('asset_id = "MH1042-MH1043"', ""), "asset_id", "required field is missing"),
        (TOML.replace("asset_id", "asset-id"), "asset_id", "did you mean 'asset_id'"),
        (TOML.replace("2024-05-17T09:30:00", '"17/05/2024"'), "inspected_at", "ISO 8601"),
        (TOML.replace("0.5", "500"), "nominal_diameter_m", "looks like millimetres: write 0.5"),
        (TOML.replace("nominal_diameter_m = 0.5", ""), "nominal_diameter_m", "missing"),
        (TOML.replace("1.25", "-1.25"), "chainage_offset_m", "greater than or equal to 0"),
        (TOML + 'direction = "sideways"\n', "direction", "'downstream' or 'upstream'"),
        (TOML + "nominal_diameter_m = 0.6\n", "line 8", "TOML syntax error"),
        (
            TOML + '[[frames]]\nfile = "frames/f1.npy"\n[[frames]]\nfile = "frames/missing.npy"\n',
            "frames[1].file",
            "'frames/missing.npy', which is not in the archive",
        ),
        (
            TOML + '[[frames]]\nfile = "frames/f1.npy"\n[[frames]]\nfile = "inspection.toml"\n',
            "frames[1].file",
            "unsupported suffix '.toml'",
        ),
        (
            TOML
            + "".join(
                f'[[frames]]\nfile = "frames/{n}"\nodometer_m = {o}\n'
                for n, o in [("f1.npy", 0.0), ("f2.npy", 0.5), ("f10.npy", 0.2)]
            ),
            "frames[2].odometer_m",
            "odometer goes back",
        ),
        (
            TOML
            + "".join(
                f'[[frames]]\nfile = "frames/{n}"\n' + (f"time_s = {t}\n" if t is not None else "")
                for n, t in [("f1.npy", 0.0), ("f2.npy", None), ("f10.npy", 0.2)]
            ),
            "frames[1].time_s",
            "given for some frames but not for this one",
        ),
    ],
    ids=[
        "missing-asset_id",
        "misspelt-asset_id",
        "bad-date",
        "diameter-500",
        "missing-diameter",
        "negative-offset",
        "bad-direction",
        "toml-syntax",
        "missing-frame-file",
        "frame-suffix",
        "odometer-backwards",
        "time-partial",
    ],
)
def test_metadata_errors(tmp_path: Path, toml: str, field: str, message: str) -> None:
    make_frames_dir(tmp_path / "run", toml=toml)
    packed = str(zip_dir(tmp_path / "run", tmp_path / "run.zip"))
    with pytest.raises(MetadataError) as info:
        open_archive(packed, workdir=tmp_path / "work")
    assert message in str(info.value)
    assert_names(info.value, packed, "inspection.toml", field)
    assert info.value.hint
    assert list((tmp_path / "work").iterdir()) == []  # nothing left behind


def test_missing_inspection_toml(tmp_path: Path) -> None:
    make_frames_dir(tmp_path / "run")
    (tmp_path / "run" / "inspection.toml").unlink()
    with pytest.raises(MetadataError, match=r"no inspection\.toml") as info:
        open_archive(tmp_path / "run")
    assert info.value.file == "inspection.toml"
    assert info.value.archive == str(tmp_path / "run")


# --- layout errors ----------------------------------------------------------------------------


def test_both_frames_and_cloud(tmp_path: Path) -> None:
    root = tmp_path / "run"
    make_frames_dir(root)
    write_points(root / "cloud.las", cylinder_frame())
    with pytest.raises(ArchiveError, match=r"holds both frames/ and a registered cloud") as info:
        open_archive(root)
    assert "keep one" in str(info.value)
    assert_names(info.value, str(root), "cloud.las", "layout")


@pytest.mark.parametrize("with_empty_frames_dir", [False, True])
def test_neither_frames_nor_cloud(tmp_path: Path, with_empty_frames_dir: bool) -> None:
    root = tmp_path / "run"
    root.mkdir()
    (root / "inspection.toml").write_text(TOML)
    if with_empty_frames_dir:
        (root / "frames").mkdir()
        (root / "frames" / "readme.md").write_text("no frames here")
    with pytest.raises(ArchiveError) as info:
        open_archive(root)
    expected = "frames/ holds no point files" if with_empty_frames_dir else "holds neither"
    assert expected in str(info.value)
    assert_names(info.value, str(root), "frames/", "layout")


def test_several_root_point_files(tmp_path: Path) -> None:
    root = tmp_path / "run"
    root.mkdir()
    (root / "inspection.toml").write_text(TOML)
    write_points(root / "a.las", cylinder_frame())
    write_points(root / "b.las", cylinder_frame())
    with pytest.raises(ArchiveError, match="2 point files at its root") as info:
        open_archive(root)
    assert_names(info.value, str(root), "b.las", "layout")


def test_not_an_archive(tmp_path: Path) -> None:
    path = tmp_path / "run.zip"
    path.write_text("not a zip")
    with pytest.raises(ArchiveError, match=r"not a directory, \.zip, \.tar"):
        open_archive(path)
    with pytest.raises(ArchiveError, match="does not exist"):
        open_archive(tmp_path / "nowhere.zip")


# --- unsafe members ---------------------------------------------------------------------------


def _zip_with(tmp_path: Path, member: str, *, symlink: bool = False) -> Path:
    make_frames_dir(tmp_path / "src")
    path = zip_dir(tmp_path / "src", tmp_path / "evil.zip")
    with zipfile.ZipFile(path, "a") as zf:
        info = zipfile.ZipInfo(member)
        if symlink:
            info.external_attr = (stat.S_IFLNK | 0o777) << 16
        zf.writestr(info, "/etc/passwd" if symlink else np.zeros(3).tobytes())
    return path


def _tar_with(tmp_path: Path, info: tarfile.TarInfo, data: bytes = b"") -> Path:
    make_frames_dir(tmp_path / "src")
    path = tar_dir(tmp_path / "src", tmp_path / "evil.tar.gz", "w:gz")
    # Rewrite with the extra member *last*, so that safe members come first.
    with tarfile.open(path) as tf:
        members = [(m, tf.extractfile(m).read() if m.isfile() else None) for m in tf]
    with tarfile.open(path, "w:gz") as tf:
        for member, content in members:
            tf.addfile(member, io.BytesIO(content) if content is not None else None)
        info.size = len(data)
        tf.addfile(info, io.BytesIO(data) if data else None)
    return path


def _symlink(name: str, target: str, kind: bytes = tarfile.SYMTYPE) -> tarfile.TarInfo:
    info = tarfile.TarInfo(name)
    info.type = kind
    info.linkname = target
    return info


def _device(name: str) -> tarfile.TarInfo:
    info = tarfile.TarInfo(name)
    info.type = tarfile.CHRTYPE
    info.devmajor, info.devminor = 1, 3
    return info


@pytest.mark.parametrize(
    ("build", "member", "why"),
    [
        (lambda p: _zip_with(p, "../evil.npy"), "../evil.npy", "'..' component"),
        (lambda p: _zip_with(p, "frames/../../evil.npy"), "frames/../../evil.npy", "'..'"),
        (lambda p: _zip_with(p, "..\\evil.npy"), "..\\evil.npy", "'..' component"),
        (lambda p: _zip_with(p, "/tmp/evil.npy"), "/tmp/evil.npy", "absolute path"),
        (lambda p: _zip_with(p, "frames/f0.npy", symlink=True), "frames/f0.npy", "symlink"),
        (
            lambda p: _tar_with(p, tarfile.TarInfo("../evil.npy"), b"x" * 8),
            "../evil.npy",
            "'..' component",
        ),
        (
            lambda p: _tar_with(p, tarfile.TarInfo("/tmp/evil.npy"), b"x" * 8),
            "/tmp/evil.npy",
            "absolute path",
        ),
        (
            lambda p: _tar_with(p, _symlink("frames/f0.npy", "/etc/passwd")),
            "frames/f0.npy",
            "symlink to '/etc/passwd'",
        ),
        (
            lambda p: _tar_with(p, _symlink("frames/f0.npy", "frames/f1.npy", tarfile.LNKTYPE)),
            "frames/f0.npy",
            "hardlink",
        ),
        (lambda p: _tar_with(p, _device("frames/null")), "frames/null", "device"),
    ],
    ids=[
        "zip-dotdot",
        "zip-nested-dotdot",
        "zip-backslash-dotdot",
        "zip-absolute",
        "zip-symlink",
        "tar-dotdot",
        "tar-absolute",
        "tar-symlink",
        "tar-hardlink",
        "tar-device",
    ],
)
def test_unsafe_members_reject_the_archive(tmp_path: Path, build, member: str, why: str) -> None:
    path = str(build(tmp_path))
    work = tmp_path / "work"
    with pytest.raises(ArchiveError) as info:
        open_archive(path, workdir=work)
    err = info.value
    assert "unsafe path" in str(err)
    assert why in str(err)
    assert_names(err, path, member, "path")
    # Nothing was extracted anywhere: not next to the archive, not in the work directory.
    assert not (tmp_path / "evil.npy").exists()
    assert list(work.iterdir()) == []


def test_extraction_never_touches_the_source(tmp_path: Path) -> None:
    make_frames_dir(tmp_path / "src")
    packed = tar_dir(tmp_path / "src", tmp_path / "run.tar")
    shutil.rmtree(tmp_path / "src")
    before = sorted(p.name for p in tmp_path.iterdir())
    with open_archive(packed) as arc:
        assert arc.frame_count == 3
        assert not arc.root.is_relative_to(tmp_path)
    assert sorted(p.name for p in tmp_path.iterdir()) == before


# --- inspection.toml details ------------------------------------------------------------------


def _meta(text: str):
    return parse_inspection_toml(text, archive="run.zip")


def test_inspection_toml_value_forms() -> None:
    base = "nominal_diameter_m = 0.5\n"
    meta = _meta(base + "asset_id = 1042\ninspected_at = 2024-05-17\n")
    assert meta.asset_id == "1042"  # a numeric id is kept as text
    assert meta.inspected_at == datetime(2024, 5, 17)
    meta = _meta(base + 'asset_id = "A"\ninspected_at = "2024-05-17T09:30:00+02:00"\n')
    assert meta.inspected_at == datetime(2024, 5, 17, 7, 30, tzinfo=UTC)
    meta = _meta('asset_id = "A"\ninspected_at = 2024-05-17\npipe_shape = "Egg"\n')
    assert meta.pipe_shape == "egg"
    assert math.isnan(meta.nominal_diameter_m)  # only circular pipes need it
    # The odometer may step back within the tolerance (cable slack).
    frames = "".join(
        f'[[frames]]\nfile = "frames/{i}.npy"\nodometer_m = {o}\n'
        for i, o in enumerate([0.0, 0.10, 0.09, 0.2])
    )
    meta = _meta(base + 'asset_id = "A"\ninspected_at = 2024-05-17\n' + frames)
    assert [f.odometer_m for f in meta.frames] == [0.0, 0.10, 0.09, 0.2]
    assert meta.odometer_uncertainty_ratio is None  # registration's default applies
    meta = _meta(
        base + 'asset_id = "A"\ninspected_at = 2024-05-17\nodometer_uncertainty_ratio = 0.05\n'
    )
    assert meta.odometer_uncertainty_ratio == 0.05
    assert meta.odometer_slip_m is None  # no slip stated
    meta = _meta(base + 'asset_id = "A"\ninspected_at = 2024-05-17\nodometer_slip_m = 0.25\n')
    assert meta.odometer_slip_m == 0.25


@pytest.mark.parametrize(
    ("extra", "field", "message"),
    [
        ("inspected_at = 09:30:00\n", "inspected_at", "without a date"),
        ("[frames]\nfile = 'a.npy'\n", "frames", "valid list"),
        ("[[frames]]\nfile = 'a.npy'\n[[frames]]\nfile = './a.npy'\n", "frames[1].file", "twice"),
        ("[[frames]]\nfile = '../a.npy'\n", "frames[0].file", "not a path inside"),
        (
            "[[frames]]\nfile = 'a.npy'\ntime_s = 1.0\n[[frames]]\nfile = 'b.npy'\ntime_s = 0.5\n",
            "frames[1].time_s",
            "time goes backwards",
        ),
        ("chainage_offset_m = nan\n", "chainage_offset_m", "finite"),
        ("nominal_diameter_m = 0.02\n", "nominal_diameter_m", "not a plausible pipe diameter"),
        ("odometer_uncertainty_ratio = 3\n", "odometer_uncertainty_ratio", "less than or equal"),
        ("odometer_uncertainty_ratio = 0\n", "odometer_uncertainty_ratio", "greater than 0"),
        ("odometer_slip_m = -0.1\n", "odometer_slip_m", "greater than or equal to 0"),
        ("odometer_slip_m = 20\n", "odometer_slip_m", "less than or equal to 10"),
        ("odometer_slip_m = inf\n", "odometer_slip_m", "finite"),
    ],
)
def test_inspection_toml_errors(extra: str, field: str, message: str) -> None:
    text = 'asset_id = "A"\n'
    if "inspected_at" not in extra:
        text += "inspected_at = 2024-05-17\n"
    if "nominal_diameter_m" not in extra:
        text += "nominal_diameter_m = 0.5\n"
    with pytest.raises(MetadataError) as info:
        _meta(text + extra)
    assert message in str(info.value)
    assert_names(info.value, "run.zip", "inspection.toml", field)


# --- the IMU's gravity direction ----------------------------------------------------------------


def test_gravity_is_read_and_normalised() -> None:
    head = 'asset_id = "A"\ninspected_at = 2024-05-17\nnominal_diameter_m = 0.5\n'
    frames = "".join(
        f'[[frames]]\nfile = "frames/{i}.npy"\ngravity = {g}\n'
        for i, g in enumerate(["[0, 0, -9.81]", "[3.0, 0.0, -4.0]"])
    )
    meta = _meta(head + frames)
    assert meta.frames[0].gravity == (0.0, 0.0, -1.0)
    assert meta.frames[1].gravity == pytest.approx((0.6, 0.0, -0.8))
    assert _meta(head + '[[frames]]\nfile = "frames/0.npy"\n').frames[0].gravity is None
    # An IMU that missed a frame: that frame has no gravity, the others keep theirs.
    gap = _meta(head + frames.replace("gravity = [3.0, 0.0, -4.0]\n", "", 1))
    assert gap.frames[0].gravity == (0.0, 0.0, -1.0) and gap.frames[1].gravity is None


@pytest.mark.parametrize(
    ("frames", "field", "message"),
    [
        ("gravity = [0, 0, 0]\n", "frames[0].gravity", "non-zero direction"),
        ("gravity = [0.0, -1.0]\n", "frames[0].gravity", "3 components"),
        ("gravity = [0.0, nan, -1.0]\n", "frames[0].gravity[1]", "finite"),
        ("gravity = [0.0, 'down', -1.0]\n", "frames[0].gravity[1]", "valid number"),
    ],
)
def test_gravity_errors(frames: str, field: str, message: str) -> None:
    text = 'asset_id = "A"\ninspected_at = 2024-05-17\nnominal_diameter_m = 0.5\n'
    with pytest.raises(MetadataError) as info:
        _meta(text + "[[frames]]\nfile = 'a.npy'\n" + frames)
    assert message in str(info.value)
    assert_names(info.value, "run.zip", "inspection.toml", field)
    assert "gravity" in str(info.value.hint)


def test_simulated_archive_carries_the_imu_gravity(tmp_path: Path) -> None:
    from pipescan.simulator.archive import write_simulated_archive
    from pipescan.simulator.scan import get_scenario, simulate_scan

    scan = simulate_scan(
        get_scenario(
            "clean", travel_m=0.1, points_per_s=20_000, imu_noise_deg=0.05, imu_dropout_ratio=0
        ),
        seed=2,
    )
    write_simulated_archive(scan, tmp_path / "sim")
    with open_archive(tmp_path / "sim") as arc:
        gravity = np.array([f.gravity for f in arc.meta.frames])
    # The true "down" seen from the true attitude, within the IMU's noise (0.05° per axis).
    down_sensor = -scan.T_world_sensor[:, 2, :3]
    angle_deg = np.degrees(np.arccos(np.clip(np.sum(gravity * down_sensor, axis=1), -1, 1)))
    assert len(gravity) == len(scan) and angle_deg.max() < 0.3
    np.testing.assert_allclose(np.linalg.norm(gravity, axis=1), 1.0)
