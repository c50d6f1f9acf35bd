"""The markers[skin] node on tiny synthetic render / taxels artifacts, one per dispatch path."""
import cv2
import numpy as np
import pytest

import stages.markers.unify as unify
from stages.common import InputError
from marker_looks import gelsight_frame, tactip_frame
from stages.markers.segment import iou, segment
from stages.markers.uskin import MID_SCALE, signal_to_marker
from stages.markers.unify import marker_sequence, segmentation_params
from tests.helpers import concat, drain


class Art(dict):
    """A dict of arrays with attrs, as the engine's artifacts look to a node."""

    def __init__(self, data, attrs=None):
        super().__init__(data)
        self.attrs = attrs or {}


def labels(n):
    return {"force": np.linspace(0, -3, 3 * n, dtype=np.float32).reshape(n, 3),
            "depth": np.array([0.2, 0.8, 0.4, 1.0, 0.6, 0.1, 0.3][:n]),
            "contact_id": np.array([0, 0, 0, 1, 1, 2, 2][:n], np.int32),
            "indenter_id": np.array([1, 1, 1, 0, 0, 1, 1][:n], np.int16),
            "phase": np.zeros(n, np.int8), "paired": np.arange(n) % 2 == 0,
            "frame": np.arange(n, dtype=np.int64) + 40}


def run(gen):
    """(chunks, the final mapping with the chunks' arrays joined in)."""
    chunks, out = drain(gen)
    return chunks, {**out, **concat(chunks)}


def assert_labels_copied(out, source):
    for key, value in labels(len(out["images"])).items():
        assert np.array_equal(out[key], source[key]) and out[key].dtype == value.dtype, key


def is_png(data):
    img = cv2.imdecode(np.asarray(data, np.uint8), cv2.IMREAD_UNCHANGED)
    return img is not None and img.ndim >= 2


def test_look_none_copies_truth(monkeypatch):
    monkeypatch.setattr(unify, "CHUNK", 2)
    rng = np.random.default_rng(0)
    truth = np.where(rng.random((5, 24, 32)) > 0.8, 255, 0).astype(np.uint8)
    source = Art({"truth": truth, "truth_reference": truth[0] // 255 * 255,
                  "indenters": np.array(["sphere", "prism"]), **labels(5)})
    chunks, out = run(marker_sequence(source=source, skin="Array1", spec={"look": "none"},
                                      segmentation={}))
    assert [len(c["images"]) for c in chunks] == [2, 2, 1]
    assert np.array_equal(out["images"], truth) and out["images"] is not truth
    assert np.array_equal(out["reference"], source["truth_reference"])
    assert_labels_copied(out, source)
    assert list(out["indenters"]) == ["sphere", "prism"]
    assert "metrics" not in out and is_png(out["figures"]["examples"])
    assert out["attrs"]["look"] == "none" and out["attrs"]["image_size"] == [24, 32]


@pytest.mark.parametrize("look, make", [("gelsight", gelsight_frame), ("tactip", tactip_frame)])
def test_camera_looks_segment_and_score(look, make):
    frames = [make(seed) for seed in range(3)]
    ref_raw, ref_truth = make(9)
    source = Art({"raw": np.stack([f[0] for f in frames]), "truth": np.stack([f[1] for f in frames]),
                  "raw_reference": ref_raw, "truth_reference": ref_truth, **labels(3)})
    segmentation = {"threshold": 20.0, "gelsight": {"edge_level": 0.5}, "tactip": {"box_margin": 3}}
    _, out = run(marker_sequence(source=source, skin=f"{look}-X", spec={"look": look},
                                 segmentation=segmentation))
    polarity = unify.POLARITY[look]
    params = segmentation_params(segmentation, look)
    assert params["polarity"] == polarity
    expect = np.stack([segment(r, **params) for r in source["raw"]])
    assert np.array_equal(out["images"], expect)
    assert iou(out["reference"], ref_truth) >= 0.9
    metrics = out["metrics"]
    assert set(metrics) == {f"segment/{look}-X/iou", f"segment/{look}-X/centroid_px"}
    assert metrics[f"segment/{look}-X/iou"] == pytest.approx(
        np.mean([iou(p, t) for p, t in zip(expect, source["truth"])]))
    assert metrics[f"segment/{look}-X/iou"] >= 0.9
    assert metrics[f"segment/{look}-X/centroid_px"] < 1.0
    assert_labels_copied(out, source)
    assert out["attrs"]["segmentation"]["polarity"] == polarity
    # the examples sheet shows raw | segmented | truth for each example frame
    sheet = cv2.imdecode(np.asarray(out["figures"]["examples"], np.uint8), cv2.IMREAD_COLOR)
    assert sheet.shape[1] == 3 * 128 + 4 * 2


def test_segmentation_params_merge():
    seg = {"threshold": 15.0, "box_margin": 2, "gelsight": {"threshold": 25.0},
           "tactip": {"polarity": "dark"}}
    assert segmentation_params(seg, "gelsight") == {"polarity": "dark", "threshold": 25.0, "box_margin": 2}
    assert segmentation_params(seg, "tactip") == {"polarity": "dark", "threshold": 15.0, "box_margin": 2}
    assert segmentation_params({}, "tactip") == {"polarity": "bright"}


@pytest.mark.parametrize("variant", ["3axis", "z"])
def test_taxel_look_draws_signals(variant):
    n = 4
    rng = np.random.default_rng(1)
    baseline = np.full((16, 3), MID_SCALE, np.int32) + rng.integers(-50, 50, (16, 3)).astype(np.int32)
    signals = baseline + rng.integers(-3000, 3000, (n, 16, 3)).astype(np.int32)
    source = Art({"signals": signals, "baseline": baseline, **labels(n)},
                 attrs={"variant": variant, "pad_mm": [24.6, 22.6]})
    spec = {"look": "taxel", "size": [64, 80], "s_xy": 2000.0, "s_z": 100.0, "base_area": 3.0,
            "min_area": 1.0, "max_area": 12.0, "max_offset": 0.8}
    _, out = run(marker_sequence(source=source, skin=f"uskin-{variant}", spec=spec, segmentation={}))
    kw = {k: spec[k] for k in ("s_xy", "s_z", "base_area", "min_area", "max_area", "max_offset")}
    expect = signal_to_marker(signals, baseline, size=(64, 80), z_only=variant == "z", **kw)
    assert np.array_equal(out["images"], expect) and out["images"].shape == (n, 64, 80)
    # readings 3000 under the rest shrink dots below base_area: min_area reached the drawing
    assert not np.array_equal(out["images"], signal_to_marker(
        signals, baseline, size=(64, 80), z_only=variant == "z",
        **{k: v for k, v in kw.items() if k != "min_area"}))
    assert out["attrs"]["settings"]["min_area"] == 1.0
    assert np.array_equal(out["reference"], signal_to_marker(baseline, baseline, size=(64, 80), **kw))
    assert cv2.connectedComponents(out["reference"])[0] - 1 == 16
    assert_labels_copied(out, source)
    assert "metrics" not in out and out["attrs"]["settings"]["z_only"] == (variant == "z")
    assert is_png(out["figures"]["examples"])


def test_errors_name_the_culprit():
    source = Art({"truth": np.zeros((2, 8, 8), np.uint8), "truth_reference": np.zeros((8, 8), np.uint8)})
    with pytest.raises(InputError, match=r"sensors.s.look must be one of none, gelsight, tactip, taxel, got 'infrared'"):
        run(marker_sequence(source=source, skin="s", spec={"look": "infrared"}, segmentation={}))
    with pytest.raises(KeyError, match=r"markers\[g\]: look 'gelsight' needs raw, raw_reference"):
        run(marker_sequence(source=source, skin="g", spec={"look": "gelsight"}, segmentation={}))
    taxels = Art({"signals": np.zeros((1, 16, 3), np.int32), "baseline": np.zeros((16, 3), np.int32)})
    with pytest.raises(KeyError, match=r"markers\[u\]: the taxel look needs `size`"):
        run(marker_sequence(source=taxels, skin="u", spec={"look": "taxel"}, segmentation={}))
