"""Nothing silently wrong, nothing lost: one frame rule, atomic files, resumable recording, and a
reconstruction that survives a bad frame or an interrupt with its summary written."""

import csv
import json
import os

import cv2
import numpy as np
import pytest

from pipeline.io.atomic import atomic_open, atomic_write_text, is_temp_name
from pipeline.design import load_design
from pipeline.errors import SourceError
from pipeline.batch import reconstruct
from pipeline.runner import Reconstructor
from pipeline.io.sources import FrameSource, open_source, record
from pipeline.types import StereoFrame
from stereotactip.cli import main
from synth_frames import gaussian_press_markers, nominal_calibration, synth_stereo_frame


def _img(k, shape=(480, 1280, 3)):
    return np.random.default_rng(k).integers(0, 256, shape, dtype=np.uint8)


# ----- atomic writes -------------------------------------------------------------------------

def test_atomic_write_keeps_the_old_file_when_the_writer_fails(tmp_path):
    p = tmp_path / "result.json"
    atomic_write_text(p, "old\n")
    with pytest.raises(KeyboardInterrupt):
        with atomic_open(p, "w") as fh:
            fh.write("half of the new")
            raise KeyboardInterrupt
    assert p.read_text() == "old\n"
    assert os.listdir(tmp_path) == ["result.json"]      # the temporary file is gone too


def test_atomic_write_temp_file_lives_beside_the_target_and_is_never_a_frame(tmp_path):
    seen = []
    with atomic_open(tmp_path / "frame_000000.png", "wb") as fh:
        seen = os.listdir(tmp_path)
        fh.write(b"x")
    assert len(seen) == 1 and is_temp_name(seen[0]) and seen[0] != "frame_000000.png"
    # a temp file left by a killed writer is not taken for a frame
    cv2.imwrite(str(tmp_path / "frame_000000.png"), _img(0))
    (tmp_path / seen[0]).write_bytes(b"partial")
    assert len(list(open_source(tmp_path))) == 1


# ----- one frame rule for every reader -------------------------------------------------------

@pytest.mark.parametrize("shape", [(480, 640, 3), (480, 1281, 3), (481, 1280), (480, 640)])
def test_detect_and_reconstruct_refuse_the_same_frames(shape, tmp_path, capsys):
    p = tmp_path / "odd.png"
    cv2.imwrite(str(p), np.zeros(shape, np.uint8))
    assert main(["detect", str(p), "--out", str(tmp_path)]) == 2
    err_detect = capsys.readouterr().err
    assert "odd.png" in err_detect and "1280x480" in err_detect
    cal = tmp_path / "calib.yaml"
    nominal_calibration(load_design("hexagon127")).save_yaml(cal)
    assert main(["reconstruct", str(p), "--calib", str(cal), "--out", str(tmp_path / "o")]) == 2
    assert "1280x480" in capsys.readouterr().err


def test_bgra_frames_are_read_alike_by_detect_and_reconstruct(tmp_path, capsys):
    bgr = _img(3)
    bgra = np.dstack([bgr, np.full((480, 1280), 255, np.uint8)])
    p = tmp_path / "frame_0000.png"
    cv2.imwrite(str(p), bgra)
    assert main(["detect", str(p), "--json", "--out", str(tmp_path / "ann")]) == 0
    rep = json.loads(capsys.readouterr().out)
    assert set(rep["views"]) == {"left", "right"} and rep["width_px"] == 1280
    (frame,) = list(open_source(p))
    np.testing.assert_array_equal(frame.image, bgr)   # alpha dropped, colour untouched


def test_a_frame_without_markers_does_not_report_a_depth(tmp_path):
    design = load_design("hexagon127")
    calib = nominal_calibration(design)
    res = Reconstructor(design, calib).process(StereoFrame(np.zeros((480, 1280), np.uint8)))
    line = res.summary(design)
    assert "0.000 mm" not in line and "NO MARKERS" in line and np.isnan(res.max_abs_dz_mm(design))
    summary = reconstruct([StereoFrame(np.zeros((480, 1280), np.uint8), index=4)], Reconstructor(design, calib),
                          tmp_path, progress=False, echo=lambda s: None)
    assert summary["per_frame"][0]["max_abs_dz_mm"] is None and summary["no_markers"] == [4]


# ----- record: atomic frames, resume ---------------------------------------------------------

class _Frames(FrameSource):
    def __init__(self, first, n, t0=0.0, fail=None):
        super().__init__("test", "test")
        self.first, self.n, self.t0, self.fail = first, n, t0, fail

    def _frames(self):
        for k in range(self.n):
            yield StereoFrame(_img(self.first + k), timestamp_s=self.t0 + 0.1 * k, index=k, source=self.name)
        if self.fail is not None:
            raise self.fail


def _rows(out):
    with open(out / "timestamps.csv", newline="") as fh:
        return list(csv.DictReader(fh))


def test_record_resume_appends_after_the_last_complete_frame(tmp_path):
    out = tmp_path / "rec"
    with pytest.raises(KeyboardInterrupt):
        record(_Frames(0, 4, fail=KeyboardInterrupt()), out, progress=False)
    # a recording cut off mid-frame by an older writer: frame 3 truncated, a torn csv line after it
    data = (out / "frame_000003.png").read_bytes()
    (out / "frame_000003.png").write_bytes(data[: len(data) // 2])
    with open(out / "timestamps.csv", "a") as fh:
        fh.write("4,0.4")
    with pytest.raises(SourceError, match="--resume"):
        record(_Frames(10, 1), out, progress=False)
    assert record(_Frames(10, 5, t0=100.0), out, max_frames=6, progress=False, resume=True) == 3
    rows = _rows(out)
    assert [r["file"] for r in rows] == [f"frame_{k:06d}.png" for k in range(6)]
    t = [float(r["timestamp_s"]) for r in rows]
    assert np.all(np.diff(t) > 0) and t[:3] == pytest.approx([0.0, 0.1, 0.2])
    assert t[3] == pytest.approx(0.3) and t[5] == pytest.approx(0.5)   # continues one interval later
    back = list(open_source(out))
    expect = [0, 1, 2, 10, 11, 12]
    for f, k in zip(back, expect, strict=True):
        np.testing.assert_array_equal(f.image, _img(k))


def test_cli_record_resume(tmp_path, capsys):
    src = tmp_path / "src"
    src.mkdir()
    for k in range(3):
        cv2.imwrite(str(src / f"img_{k}.png"), _img(k))
    out = tmp_path / "rec"
    assert main(["record", str(src), "--out", str(out), "--max-frames", "2", "--quiet"]) == 0
    assert main(["record", str(src), "--out", str(out), "--max-frames", "4", "--quiet", "--resume"]) == 0
    assert "now holds 4" in capsys.readouterr().out
    assert len(_rows(out)) == 4


def test_a_frame_is_never_half_written(tmp_path, monkeypatch):
    import pipeline.io.atomic as atomic

    out = tmp_path / "rec"

    real_replace = os.replace

    def killed(src, dst):
        if str(dst).endswith(".png"):
            raise KeyboardInterrupt      # the process dies between writing the frame and renaming it
        real_replace(src, dst)
    monkeypatch.setattr(atomic.os, "replace", killed)
    with pytest.raises(KeyboardInterrupt):
        record(_Frames(0, 2), out, progress=False)
    monkeypatch.undo()
    assert sorted(out.iterdir()) == [out / "timestamps.csv"] and _rows(out) == []


# ----- reconstruct: a bad frame is skipped and named, the summary always written ---------------

@pytest.fixture(scope="module")
def recording(tmp_path_factory):
    d = tmp_path_factory.mktemp("rec")
    design = load_design("hexagon127")
    calib = nominal_calibration(design)
    calib.save_yaml(d / "calib.yaml")
    frames = d / "frames"
    frames.mkdir()
    rng = np.random.default_rng(2)
    for k, depth in enumerate((0.0, 1.0, 2.0)):
        f = synth_stereo_frame(design, calib, gaussian_press_markers(design, depth), rng=rng)
        cv2.imwrite(str(frames / f"frame_{k:06d}.png"), f.image)
    return d


def test_reconstruct_skips_an_unreadable_frame_and_names_it(recording, tmp_path, capsys):
    frames = tmp_path / "frames"
    frames.mkdir()
    for p in (recording / "frames").iterdir():
        (frames / p.name).write_bytes(p.read_bytes())
    data = (frames / "frame_000001.png").read_bytes()
    (frames / "frame_000001.png").write_bytes(data[:1000])       # cut off mid-write
    out = tmp_path / "out"
    rc = main(["reconstruct", str(frames), "--calib", str(recording / "calib.yaml"), "--out", str(out)])
    text = capsys.readouterr().out
    assert rc == 0 and "frame_000001.png" in text and "SKIPPED" in text
    summary = json.loads((out / "summary.json").read_text())
    assert summary["frames"] == 2 and [s["file"] for s in summary["skipped"]] == ["frame_000001.png"]
    assert [f["index"] for f in summary["per_frame"]] == [0, 2] and summary["stopped"] is None


def test_reconstruct_runs_its_frames_at_the_niceness_asked_for(recording, tmp_path, monkeypatch, capsys):
    """`reconstruct --nice N` processes the frames at niceness N and restores the caller's afterwards; a
    niceness the OS refuses is a clear error (exit 2), not a silent run at the old priority. (Run in a thread
    of its own: niceness is per thread, so the test process keeps its own.)"""
    import threading

    from pipeline.priority import current_niceness

    seen = []
    real = Reconstructor.process

    def process(self, frame):
        seen.append(current_niceness())
        return real(self, frame)

    def run(out, nice):
        result = {}
        t = threading.Thread(target=lambda: result.update(
            rc=main(["reconstruct", str(recording / "frames"), "--calib", str(recording / "calib.yaml"),
                     "--out", str(out), "--nice", str(nice)]), after=current_niceness()))
        t.start()
        t.join()
        return result

    monkeypatch.setattr(Reconstructor, "process", process)
    before = current_niceness()
    if before > 17:
        pytest.skip(f"the tests run at niceness {before}: no niceness two above it to ask for (the OS caps it at 19)")
    result = run(tmp_path / "o", before + 2)
    assert result["rc"] == 0 and seen == [before + 2] * 3
    if os.geteuid() == 0:                   # lowering it back needs the privilege
        assert result["after"] == before

    def refuse(*_):
        raise PermissionError(1, "Operation not permitted")

    monkeypatch.setattr(os, "setpriority", refuse)
    assert run(tmp_path / "o2", -10)["rc"] == 2 and "CAP_SYS_NICE" in capsys.readouterr().err


def test_reconstruct_holds_the_cpu_latency_asked_for_while_it_processes_frames(recording, tmp_path, monkeypatch,
                                                                              capsys):
    """`reconstruct --cpu-latency US` holds the PM QoS request while every frame is processed (a stand-in file
    for the kernel's device records what was asked), and a system without the device is a clear error (exit 2)."""
    import struct

    import pipeline.priority as priority

    dev = tmp_path / "cpu_dma_latency"
    dev.write_bytes(struct.pack("=i", 2_000_000_000))
    monkeypatch.setattr(priority, "PM_QOS_DEVICE", str(dev))
    seen = []
    real = Reconstructor.process

    def process(self, frame):
        seen.append(struct.unpack("=i", dev.read_bytes())[0])
        return real(self, frame)

    monkeypatch.setattr(Reconstructor, "process", process)
    args = ["reconstruct", str(recording / "frames"), "--calib", str(recording / "calib.yaml")]
    assert main(args + ["--out", str(tmp_path / "o"), "--cpu-latency", "0"]) == 0 and seen == [0] * 3
    monkeypatch.setattr(priority, "PM_QOS_DEVICE", str(tmp_path / "missing"))
    assert main(args + ["--out", str(tmp_path / "o2"), "--cpu-latency", "0"]) == 2
    assert "Linux only" in capsys.readouterr().err


def test_interrupted_reconstruction_still_writes_its_summary(recording, tmp_path):
    design = load_design("hexagon127")
    calib = nominal_calibration(design)
    first = next(iter(open_source(recording / "frames")))

    def frames():
        yield first
        raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        reconstruct(frames(), Reconstructor(design, calib), tmp_path, progress=False, echo=lambda s: None)
    summary = json.loads((tmp_path / "summary.json").read_text())
    assert summary["frames"] == 1 and summary["stopped"] == "interrupted"
    assert not [p for p in os.listdir(tmp_path) if is_temp_name(p)]


# ----- one writer for every output -----------------------------------------------------------

def test_no_output_is_written_in_place():
    """Every file the project produces goes through pipeline.io.atomic: no module opens a final path for
    writing (the patterns below are every way the code base used to)."""
    import re
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]
    forbidden = [r"\.write_text\(", r"\.write_bytes\(", r"cv2\.imwrite\(", r"\bopen\([^)]*[\"'][wax]b?[\"']",
                 r"\.savefig\(\s*(?!buf\b)", r"np\.savez(_compressed)?\(\s*(?!fh\b)", r"\.export\(\s*str\(",
                 r"FILE_STORAGE_WRITE\)"]
    offenders = []
    for folder in ("pipeline", "twin", "benchmarks", "stereotactip", "sim_assets"):
        for path in (root / folder).rglob("*.py"):
            if path.name == "atomic.py":
                continue
            lines = path.read_text().splitlines()
            for n, line in enumerate(lines, 1):
                if line.rstrip().endswith("# append-only"):   # timestamps.csv: rows appended, flushed
                    continue
                if re.search(r"np\.savez(_compressed)?\(\s*$", line):   # arguments on the next line
                    line = line + lines[n].strip()
                if any(re.search(p, line) for p in forbidden):
                    offenders.append(f"{path.relative_to(root)}:{n}: {line.strip()}")
    assert not offenders, "outputs written in place:\n" + "\n".join(offenders)


@pytest.mark.parametrize("content", [b"index,timestamp_s,file\n0,nan,frame_000000.png\n", b"\xff\xfe\x00\x01garbage"])
def test_malformed_timestamps_are_a_source_error(tmp_path, content):
    cv2.imwrite(str(tmp_path / "frame_000000.png"), _img(0))
    (tmp_path / "timestamps.csv").write_bytes(content)
    with pytest.raises(SourceError, match="timestamps.csv"):
        open_source(tmp_path)


@pytest.mark.parametrize("argv", [["--square-mm", "nan"], ["--square-mm", "-4"]])
def test_calibrate_refuses_a_board_without_size(tmp_path, argv, capsys):
    with pytest.raises(SystemExit) as info:
        main(["calibrate", str(tmp_path), *argv])
    assert info.value.code == 2 and "--square-mm" in capsys.readouterr().err


def test_result_readers_name_a_truncated_file(tmp_path):
    from pipeline.io.files import read_markers_csv, read_ply_vertices, write_markers_csv, write_ply
    from pipeline.types import DataError, HeightMap, MarkerCloud

    cloud = MarkerCloud(np.arange(5), np.random.default_rng(0).normal(size=(5, 3)))
    write_markers_csv(tmp_path / "m.csv", cloud)
    write_ply(tmp_path / "a.ply", cloud.xyz_mm)
    write_ply(tmp_path / "b.ply", cloud.xyz_mm, binary=True)
    HeightMap(np.arange(3.0), np.arange(2.0), np.zeros((2, 3))).save_npz(tmp_path / "h.npz")
    np.testing.assert_allclose(read_ply_vertices(tmp_path / "a.ply"), cloud.xyz_mm, atol=1e-6)
    readers = {"m.csv": read_markers_csv, "a.ply": read_ply_vertices, "b.ply": read_ply_vertices,
               "h.npz": HeightMap.load_npz}
    for name, read in readers.items():
        data = (tmp_path / name).read_bytes()
        (tmp_path / f"cut_{name}").write_bytes(data[: len(data) * 2 // 3] if name != "m.csv" else b"\xff\xfe\x00")
        with pytest.raises(DataError, match=f"cut_{name}"):
            read(tmp_path / f"cut_{name}")


def test_a_frame_file_that_vanishes_is_skipped_like_an_unreadable_one(tmp_path):
    for k in range(3):
        cv2.imwrite(str(tmp_path / f"frame_{k:06d}.png"), _img(k))
    src = open_source(tmp_path, skip_unreadable=True)
    (tmp_path / "frame_000001.png").unlink()          # e.g. removed by hand during a long run
    assert [f.index for f in src] == [0, 2]
    assert [s["file"] for s in src.skipped] == ["frame_000001.png"] and "does not exist" in src.skipped[0]["error"]
