"""Marker patterns from image files: a drawn pattern saved as an image loads back as the same
markers; a file that is missing, unreadable, blank or markerless is one line naming it."""
import json
import os
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from stages.common import InputError
from stages.markers.pattern_files import PatternFileError, image_pattern_name, pattern_files
from stages.markers.pattern_image import load_pattern
from stages.markers.patterns import gelsight_pattern, pattern, rasterize, reference_set

ROOT = Path(__file__).resolve().parents[3]


def _save(path, img):
    assert cv2.imwrite(str(path), img)
    return str(path)


def _matched(a, b):
    """Each centroid of a with its nearest in b: the largest distance (mm)."""
    d = np.hypot(*(a.centers[:, None, :] - b.centers[None, :, :]).transpose(2, 0, 1))
    return d.min(1).max()


@pytest.mark.parametrize("name,size,suffix", [("Array2", (568, 568), ".png"), ("Circle4", (400, 400), ".png"),
                                              ("Diamond3", (300, 300), ".jpg")])
def test_a_drawn_pattern_round_trips_through_an_image(tmp_path, name, size, suffix):
    drawn = pattern(name)
    path = _save(tmp_path / f"{name}{suffix}", rasterize(drawn, size=size))
    got = load_pattern(path, pad_size_mm=drawn.pad_size_mm)
    px = drawn.pad_size_mm[0] / size[1]                                 # mm per pixel
    assert len(got) == len(drawn) and got.pad_size_mm == drawn.pad_size_mm
    assert _matched(drawn, got) < 0.25 * px and _matched(got, drawn) < 0.25 * px
    area = lambda m: np.pi * m.axes[:, 0] * m.axes[:, 1]                # noqa: E731
    assert np.median(area(got)) == pytest.approx(np.median(area(drawn)), rel=0.06)
    if name == "Circle4":                                               # tilted ellipses keep their aspect
        assert np.median(got.axes[:, 0] / got.axes[:, 1]) == pytest.approx(1.6, rel=0.08)


def test_dark_markers_on_light_and_a_captured_frame(tmp_path):
    """A GelSight's no-contact frame shows dark markers on a lit, unevenly bright gel."""
    drawn = gelsight_pattern("A-II")
    mask = rasterize(drawn, size=(240, 320)) > 0
    yy, xx = np.mgrid[0:240, 0:320]
    gel = 120 + 60 * xx / 320 + 20 * np.sin(yy / 40)                     # a shaded, uneven gel
    frame = np.where(mask, 25, gel)[..., None] * np.array([1.0, 0.9, 0.8])
    rng = np.random.default_rng(0)
    frame = np.clip(frame + rng.normal(0, 3, frame.shape), 0, 255).astype(np.uint8)
    path = _save(tmp_path / "frame.png", frame[..., ::-1])              # cv2 writes BGR
    got = load_pattern(path, pad_size_mm=drawn.pad_size_mm, polarity="dark")
    assert len(got) == 56 and _matched(drawn, got) < 0.1
    with pytest.raises(InputError, match=r"^pattern image .*frame.png: no markers found \(white on black; "
                                         r"set the sensor's pattern_polarity if they are the other way\)$"):
        load_pattern(path, pad_size_mm=drawn.pad_size_mm)


def test_a_missing_unreadable_blank_or_markerless_file_is_one_line(tmp_path):
    pad = (20.0, 20.0)
    with pytest.raises(InputError, match=r"^pattern image .*nope.png: no such file$"):
        load_pattern(str(tmp_path / "nope.png"), pad_size_mm=pad)
    (tmp_path / "junk.png").write_bytes(b"\x89PNG\r\n\x1a\n" + b"\0" * 40)
    with pytest.raises(InputError, match=r"^pattern image .*junk.png: unreadable \(not a PNG or JPEG, or truncated\)$"):
        load_pattern(str(tmp_path / "junk.png"), pad_size_mm=pad)
    blank = _save(tmp_path / "blank.png", np.full((64, 64), 7, np.uint8))
    with pytest.raises(InputError, match=r"^pattern image .*blank.png: blank \(grey levels 7..7\): no markers to see$"):
        load_pattern(blank, pad_size_mm=pad)
    half = np.zeros((64, 64), np.uint8)
    half[:, 32:] = 255                                                  # one edge, no marker
    with pytest.raises(InputError, match=r"^pattern image .*half.png: no markers found"):
        load_pattern(_save(tmp_path / "half.png", half), pad_size_mm=pad)


def test_the_listing_checksums_each_file_and_names_what_is_missing(tmp_path):
    img = rasterize(pattern("Array1"), size=(128, 128))
    mine = _save(tmp_path / "mine.png", img)
    sensors = {"a": {"pattern": mine, "pad_mm": [25.0, 25.0]}, "b": {"pattern": "Array1", "pad_mm": [20.0, 20.0]}}
    got = pattern_files(sensors=sensors, pattern_dir="", names=["Array1"])
    assert list(got) == [image_pattern_name(mine)] and got[image_pattern_name(mine)]["pad_mm"] == [25.0, 25.0]
    _save(tmp_path / "mine.png", rasterize(pattern("Array2"), size=(128, 128)))   # edited in place: another key
    assert pattern_files(sensors=sensors, pattern_dir="", names=[])[image_pattern_name(mine)]["sha256"] != \
        got[image_pattern_name(mine)]["sha256"]
    folder = tmp_path / "dir"
    folder.mkdir()
    _save(folder / "Array1.jpg", img)
    assert pattern_files(sensors=sensors, pattern_dir=str(folder), names=["Array1"])["Array1"]["pad_mm"] == [20.0, 20.0]
    with pytest.raises(PatternFileError, match=r"^patterns.dir .*dir: no Array2.jpg, .jpeg or .png$"):
        pattern_files(sensors=sensors, pattern_dir=str(folder), names=["Array1", "Array2"])
    with pytest.raises(PatternFileError, match=r"^sensors.c.pattern: pattern image .*gone.png: no such file$"):
        pattern_files(sensors={"c": {"pattern": str(tmp_path / "gone.png")}}, pattern_dir="", names=[])
    out = reference_set(["Array1"], size=(128, 128), files=pattern_files(sensors=sensors, pattern_dir=str(folder),
                                                                         names=["Array1"]))
    assert image_pattern_name(mine) in out["names"]
    assert np.mean(out["images"]["Array1"] != img) < 0.01              # the file's markers, redrawn


def _cli(*args, env=None):
    e = {**os.environ, "PYTHONPATH": str(ROOT), **(env or {})}
    e.pop("PIPELINE_STORE", None)
    return subprocess.run([sys.executable, "-m", "pipeline", *args], cwd=ROOT, env=e, capture_output=True,
                          text=True, timeout=600)


def test_the_patterns_node_reads_a_folder_and_a_sensors_file(tmp_path):
    folder = tmp_path / "marker_pattern"
    folder.mkdir()
    for name in ("Array1", "Array2", "Array3", "Array4", "Circle1", "Circle2", "Circle3", "Circle4",
                 "Diamond1", "Diamond2", "Diamond3", "Diamond4"):
        _save(folder / f"{name}.jpg", rasterize(pattern(name), size=(568, 568)))
    own = _save(tmp_path / "own.png", rasterize(gelsight_pattern("D-I"), size=(300, 300)))
    store = str(tmp_path / "store")
    args = ("--profile", "ci", "--store", store, "-p", f"patterns.dir={folder}",
            "-p", f"sensors.gelsight-A-II.pattern={own}")
    p = _cli("run", "patterns", "render[skin=gelsight-A-II]", "--json", *args)
    assert p.returncode == 0, p.stderr[-2000:]
    from pipeline.artifact import Artifact
    with Artifact(_cli("get", "patterns", *args).stdout.strip()) as art:
        assert art.attrs["files"]["Array1"]["path"] == str(folder / "Array1.jpg")
        assert len(art[f"markers/{image_pattern_name(own)}/centers"]) == 56
    (folder / "Array3.jpg").unlink()
    p = _cli("run", "patterns", *args)
    assert p.returncode == 2 and p.stderr.count("\n") == 1
    assert f"patterns.dir {folder}: no Array3.jpg, .jpeg or .png" in p.stderr
    assert json.loads(_cli("ls", "--json", "--store", store).stdout)        # the store is intact


def test_a_marker_the_border_cuts_is_left_out(tmp_path):
    """The authors' Array3.jpg has two slivers of markers at its right edge: not markers."""
    drawn = pattern("Array3")
    img = rasterize(drawn, size=(400, 400))
    img[190:200, 397:] = 255                                            # a sliver at the border
    img[100:104, 0:6] = 255
    got = load_pattern(_save(tmp_path / "cut.png", img), pad_size_mm=drawn.pad_size_mm)
    assert len(got) == len(drawn)
