"""Frame sources and lossless recording."""

import csv

import cv2
import numpy as np
import pytest

from pipeline.errors import SourceError
from pipeline.io.sources import FrameSource, open_source, record
from pipeline.types import StereoFrame


def _frame_img(k: int, *, colour=True) -> np.ndarray:
    rng = np.random.default_rng(k)
    shape = (480, 1280, 3) if colour else (480, 1280)
    return rng.integers(0, 256, shape, dtype=np.uint8)


def _folder(tmp_path, n=3, colour=True):
    d = tmp_path / "frames"
    d.mkdir()
    for k in range(n):
        cv2.imwrite(str(d / f"img_{k:03d}.png"), _frame_img(k, colour=colour))
    return d


def test_folder_source_yields_sorted_frames(tmp_path):
    d = _folder(tmp_path, 3)
    with open_source(d) as src:
        frames = list(src)
    assert [f.index for f in frames] == [0, 1, 2]
    assert [f.timestamp_s for f in frames] == [0.0, 1.0, 2.0]
    for k, f in enumerate(frames):
        assert isinstance(f, StereoFrame) and f.source == str(d)
        np.testing.assert_array_equal(f.image, _frame_img(k))


def test_single_grey_image_and_digit_string_camera_spec(tmp_path):
    p = tmp_path / "one.png"
    cv2.imwrite(str(p), _frame_img(5, colour=False))
    frames = list(open_source(str(p)))
    assert len(frames) == 1 and frames[0].image.shape == (480, 1280)
    with pytest.raises(SourceError, match="camera 97"):
        open_source("97")


def test_video_file_source(tmp_path):
    p = tmp_path / "v.avi"
    w = cv2.VideoWriter(str(p), cv2.VideoWriter_fourcc(*"MJPG"), 30.0, (1280, 480))
    if not w.isOpened():
        pytest.skip("this OpenCV build cannot write MJPG/AVI")
    for k in range(4):
        w.write(np.full((480, 1280, 3), 40 * k, np.uint8))
    w.release()
    with open_source(p) as src:
        frames = list(src)
    assert len(frames) == 4
    assert [f.index for f in frames] == [0, 1, 2, 3]
    assert np.all(np.diff([f.timestamp_s for f in frames]) > 0)  # video position advances
    # MJPEG is lossy: the grey levels come back within a few counts
    assert abs(float(frames[2].image.mean()) - 80.0) < 3.0


@pytest.mark.parametrize("shape", [(480, 640, 3), (240, 1280, 3), (480, 1281, 3)])
def test_wrong_frame_size_or_channels_names_the_file(tmp_path, shape):
    d = tmp_path / "bad"
    d.mkdir()
    cv2.imwrite(str(d / "a.png"), np.zeros((480, 1280, 3), np.uint8))
    cv2.imwrite(str(d / "b.png"), np.zeros(shape, np.uint8))
    it = iter(open_source(d))
    next(it)
    with pytest.raises(SourceError, match=r"b\.png.*frame 1"):
        next(it)


def test_16bit_and_unreadable_files(tmp_path):
    p16 = tmp_path / "deep.png"
    cv2.imwrite(str(p16), np.zeros((480, 1280), np.uint16))
    with pytest.raises(SourceError, match="8-bit"):
        list(open_source(p16))
    junk = tmp_path / "junk.png"
    junk.write_bytes(b"not a png")
    with pytest.raises(SourceError, match="junk.png.*unreadable"):
        list(open_source(junk))
    with pytest.raises(SourceError, match="no such"):
        open_source(tmp_path / "missing.png")
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(SourceError, match="no images"):
        open_source(empty)


def test_record_roundtrip_is_lossless(tmp_path):
    d = _folder(tmp_path, 4)
    out = tmp_path / "rec"
    assert record(str(d), out, max_frames=3, progress=False) == 3
    with open(out / "timestamps.csv", newline="") as fh:
        rows = list(csv.DictReader(fh))
    assert [r["file"] for r in rows] == [f"frame_{k:06d}.png" for k in range(3)]
    assert [float(r["timestamp_s"]) for r in rows] == [0.0, 1.0, 2.0]
    back = list(open_source(out))
    assert len(back) == 3
    for k, f in enumerate(back):
        np.testing.assert_array_equal(f.image, _frame_img(k))
        assert f.timestamp_s == float(k)


def test_record_refuses_to_overwrite(tmp_path):
    d = _folder(tmp_path, 2)
    out = tmp_path / "rec"
    record(d, out, progress=False)
    with pytest.raises(SourceError, match="overwrite"):
        record(d, out, progress=False)
    assert record(d, out, max_frames=1, progress=False, overwrite=True) == 1
    assert sorted(p.name for p in out.iterdir()) == ["frame_000000.png", "timestamps.csv"]


class _Failing(FrameSource):
    def __init__(self, exc):
        super().__init__("failing", "test")
        self.exc = exc

    def _frames(self):
        for k in range(3):
            yield StereoFrame(_frame_img(k), timestamp_s=0.5 * k, index=k, source=self.name)
        raise self.exc


@pytest.mark.parametrize("exc", [KeyboardInterrupt(), SourceError("failing: frame 3: broken")])
def test_interrupted_recording_keeps_what_was_written(tmp_path, exc):
    out = tmp_path / "rec"
    with pytest.raises(type(exc)):
        record(_Failing(exc), out, progress=False)
    with open(out / "timestamps.csv", newline="") as fh:
        rows = list(csv.DictReader(fh))
    assert len(rows) == 3 and [float(r["timestamp_s"]) for r in rows] == [0.0, 0.5, 1.0]
    for k in range(3):
        np.testing.assert_array_equal(cv2.imread(str(out / f"frame_{k:06d}.png")), _frame_img(k))


def test_closed_source_refuses_iteration(tmp_path):
    src = open_source(_folder(tmp_path, 1))
    src.close()
    with pytest.raises(SourceError, match="closed"):
        iter(src)


def test_folder_with_frame_files_ignores_other_images(tmp_path):
    for i in range(2):
        cv2.imwrite(str(tmp_path / f"frame_{i:04d}.png"), np.full((480, 1280, 3), 40 * i, np.uint8))
    cv2.imwrite(str(tmp_path / "preview.png"), np.zeros((300, 300, 4), np.uint8))  # not a frame
    with open_source(tmp_path) as src:
        frames = list(src)
    assert [int(f.image[0, 0, 0]) for f in frames] == [0, 40]
