"""The markers[skin] node on tiny synthetic render / taxels artifacts, one per dispatch path."""
import cv2
import numpy as np
import pytest

import stages.markers.unify as unify
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
    with pytest.raises(ValueError, match=r"markers\[s\]: look must be one of .* got 'infrared'"):
        run(marker_sequence(source=source, skin="s", spec={"look": "infrared"}, segmentation={}))
    with pytest.raises(KeyError, match=r"markers\[g\]: look 'gelsight' needs raw, raw_reference"):
        run(marker_sequence(source=source, skin="g", spec={"look": "gelsight"}, segmentation={}))
    taxels = Art({"signals": np.zeros((1, 16, 3), np.int32), "baseline": np.zeros((16, 3), np.int32)})
    with pytest.raises(KeyError, match=r"markers\[u\]: the taxel look needs `size`"):
        run(marker_sequence(source=taxels, skin="u", spec={"look": "taxel"}, segmentation={}))


# ---------------------------------------------------------------------------- references[skin]

TAKES_SPEC = {"pattern": "gelsight-A-II", "look": "gelsight", "noise": 3.0}


def _reference_shot(deform, seed, index):
    from stages.markers.patterns import gelsight_pattern
    from stages.markers.render import Renderer
    r = Renderer(deform["grid_x"], deform["grid_y"], deform["surface_z"], deform["on_pad"],
                 gelsight_pattern("A-II"), look="gelsight", size=(64, 64), noise=3.0, seed=seed)
    return segment(r.render(np.zeros((17, 17, 3), np.float32), index)["raw"],
                   **segmentation_params({}, "gelsight"))


def test_reference_takes_are_the_render_scene_shot_after_the_sequence():
    from stages.markers.mitsuba_backend import resolve_backend
    from tests.helpers import flat_pad, gelsight_patterns
    deform = {**flat_pad(), "displacement": np.zeros((5, 17, 17, 3), np.float32)}
    reference = _reference_shot(deform, 7, -1)                # the markers node's reference
    # a store rendered with LLVM: shot with it where usable, else with the scalar backend
    source = Art({}, {"seed": 7, "spp": 1, "backend": "llvm", "size": [64, 64]})
    out = unify.reference_takes(markers={"reference": reference}, source=source, deform=deform,
                                patterns=gelsight_patterns(), skin="g", spec=TAKES_SPEC,
                                segmentation={}, takes=3)
    takes = out["takes"]
    assert takes.shape == (3, 64, 64) and takes.dtype == np.uint8
    for k in range(3):                                         # frames 0..4 use indices 0..4
        assert np.array_equal(takes[k], _reference_shot(deform, 7, 5 + k))
    a = out["attrs"]
    assert a["frame_indices"] == [5, 6, 7] and a["reference_rendered_again_px"] == 0
    assert a["backend"] == resolve_backend("auto")
    assert a["pixels_differ"] == [int((t != reference).sum()) for t in takes]
    assert all(0 < d < 100 for d in a["pixels_differ"])       # a few marker-edge pixels each
    assert not np.array_equal(takes[0], takes[1])
    assert bytes(out["figures"]["takes"][:8]) == b"\x89PNG\r\n\x1a\n"


def test_reference_takes_none_for_exact_references_and_errors_name_the_skin():
    from tests.helpers import flat_pad, gelsight_patterns
    deform = {**flat_pad(), "displacement": np.zeros((2, 17, 17, 3), np.float32)}
    ref = np.zeros((32, 32), np.uint8)
    kw = dict(markers={"reference": ref}, deform=deform, patterns=gelsight_patterns(),
              segmentation={})
    out = unify.reference_takes(source=Art({}), skin="uskin-z", spec={"look": "taxel"}, takes=8, **kw)
    assert out["takes"].shape == (0, 32, 32)
    assert out["attrs"]["why_none"] == "look 'taxel' has no camera noise: its reference is exact"
    with pytest.raises(ValueError, match=r"references\[g\]: render size \[64, 64\] is not the "
                                         r"reference's \[32, 32\]"):
        unify.reference_takes(source=Art({}, {"seed": 1, "spp": 1, "backend": "auto", "size": [64, 64]}),
                              skin="g", spec=TAKES_SPEC, takes=2, **kw)
    with pytest.raises(KeyError, match=r"references\[g\]: the render's attrs lack seed, spp"):
        unify.reference_takes(source=Art({}, {"backend": "auto", "size": [32, 32]}), skin="g",
                              spec=TAKES_SPEC, takes=2, **kw)
    with pytest.raises(ValueError, match=r"references\[g\]: takes must be >= 0, got -1"):
        unify.reference_takes(source=Art({}), skin="g", spec=TAKES_SPEC, takes=-1, **kw)
