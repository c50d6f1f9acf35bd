"""Mitsuba rendering of deformed skins (stages.markers.render) on synthetic displacement fields.

Regenerate the golden images, if the look changed on purpose, with
    .venv/bin/python tests/stages/markers/test_render.py
"""
import inspect
from pathlib import Path

import cv2
import numpy as np
import pytest

from stages.markers.looks import LOOKS
from stages.markers.mitsuba_backend import llvm_usable, llvm_version, resolve_backend
from stages.markers.patterns import gelsight_pattern, pattern, rasterize, tactip_pattern
from stages.common import LABEL_KEYS, InputError
from stages.markers.render import (Renderer, camera_distance, camera_fov_x, marker_set,
                                   render_frames, render_sequence)
from tests.helpers import drain

GOLDEN = Path(__file__).parent / "golden"
PNG = b"\x89PNG\r\n\x1a\n"


def flat_pad(n=33, pad=20.0):
    g = (np.arange(n) - (n - 1) / 2) * pad / (n - 1)
    return g, g, np.zeros((n, n)), np.ones((n, n), bool)


def dome(n=41, diameter=40.0, radius=41.5):
    g = (np.arange(n) - (n - 1) / 2) * diameter / (n - 1)
    r2 = g[None, :] ** 2 + g[:, None] ** 2
    on = r2 <= (diameter / 2) ** 2
    sag = radius - np.sqrt(radius ** 2 - np.minimum(r2, (diameter / 2) ** 2))
    return g, g, np.where(on, -sag, 0.0), on


def press(gx, gy, centre=(0.0, 0.0), depth=1.0, radius=3.0, outward=0.25, shear=(0.0, 0.0)):
    """Hertz-like indentation: a dip (uz < 0) with radially outward ux, uy, plus an optional
    lateral shear of the contact region (a Gaussian patch moving with the indenter)."""
    x, y = np.meshgrid(gx - centre[0], gy - centre[1])
    bump = np.exp(-(x * x + y * y) / (2 * radius ** 2))
    drag = np.exp(-(x * x + y * y) / (2 * (1.5 * radius) ** 2))
    d = np.stack([outward * depth * x / radius * bump + shear[0] * drag,
                  outward * depth * y / radius * bump + shear[1] * drag,
                  -depth * bump], -1)
    return d.astype(np.float32)


def centroids(img):
    n, _, stats, cents = cv2.connectedComponentsWithStats(img, connectivity=8)
    return cents[1:][stats[1:, cv2.CC_STAT_AREA] >= 2]


def matched_motion(ref, img):
    """Centroids of ref and their motion to the nearest centroid in img, (col, row) px."""
    a, b = centroids(ref), centroids(img)
    d = np.linalg.norm(a[:, None] - b[None], axis=-1)
    return a, b[d.argmin(1)] - a


def iou(a, b):
    a, b = a > 0, b > 0
    return (a & b).sum() / (a | b).sum()


@pytest.fixture(scope="module")
def none_renderer():
    gx, gy, z, on = flat_pad()
    return Renderer(gx, gy, z, on, pattern("Array3"), look="none", size=(128, 128), spp=1)


def _gelsight_frame():
    """A 25 mm GelSight pad pressed 1.2 mm at (2, -1) mm and dragged 0.6 mm along +x."""
    gx, gy, z, on = flat_pad(33, 25.0)
    return gx, gy, z, on, press(gx, gy, (2.0, -1.0), depth=1.2, radius=3.0, shear=(0.6, 0.0))


@pytest.fixture(scope="module")
def gelsight_frame():
    return _gelsight_frame()


def golden_render(backend="auto"):
    gx, gy, z, on, d = _gelsight_frame()
    return render_frames(d[None], gx, gy, z, on, gelsight_pattern("C-II"), look="gelsight",
                         size=(64, 64), spp=4, backend=backend, noise=3.0, seed=11)


# -- camera -------------------------------------------------------------------------------------

def test_camera_model():
    # 35 mm lens, 36 mm film: 54.4 deg over the native 640 px; a square output crops 480x480
    assert camera_fov_x((480, 640)) == pytest.approx(54.432, abs=1e-3)
    assert camera_fov_x((128, 128)) == pytest.approx(42.184, abs=1e-3)
    # square pad, square image: the pad spans the frame exactly (13.5 mm half-film at 35 mm);
    # 4:3 frame: the pad spans the width, the rows see its middle 15 mm
    assert camera_distance((128, 128), (20, 20)) == pytest.approx(10 * 35 / 13.5, rel=1e-6)
    assert camera_distance((480, 640), (20, 20)) == pytest.approx(10 * 35 / 18, rel=1e-6)


def test_zero_displacement_truth_is_the_reference_pattern(none_renderer):
    """On a flat pad a pinhole maps the pad plane affinely onto the image, so the rest frame
    is the rasterised pattern up to edge pixels."""
    # pixel centres on shared triangle edges (a few % of rays slip through) are filled in
    rest = none_renderer.mesh.positions(np.zeros((33, 33, 3)))
    assert (none_renderer.trace(rest)[..., 2] > 0).all()
    truth = none_renderer.render(np.zeros((33, 33, 3)))["truth"]
    assert truth.dtype == np.uint8 and set(np.unique(truth)) == {0, 255}
    ref = rasterize(pattern("Array3"), size=(128, 128))
    assert iou(truth, ref) >= 0.9
    assert len(centroids(truth)) == 80
    np.testing.assert_allclose(np.sort(centroids(truth), 0), np.sort(centroids(ref), 0), atol=0.25)


def test_dome_perspective_pulls_central_pins_inwards():
    """TacTip: the camera frames the dome's rim; the apex lies 5 mm further away, so central
    pins image closer to the centre than the orthographic reference - an IoU with rasterize
    is not the right check, a radial scale that grows towards the rim is."""
    gx, gy, z, on = dome()
    out = render_frames(np.zeros((1, 41, 41, 3)), gx, gy, z, on, tactip_pattern(), look="tactip",
                        size=(128, 128), spp=1)
    img, ref = out["truth"][0], rasterize(tactip_pattern(), size=(128, 128))
    assert len(centroids(img)) == 127 and out["raw"].shape == (1, 128, 128, 3)
    a, b = centroids(ref) - 63.5, centroids(img) - 63.5
    pair = np.linalg.norm(a[:, None] - b[None], axis=-1).argmin(1)
    r_ref, r_img = np.hypot(*a.T), np.hypot(*b[pair].T)
    far = r_ref > 10
    scale = r_img[far] / r_ref[far]
    assert np.all(scale < 1.0)
    inner, outer = r_ref[far] < 30, r_ref[far] > 45
    assert scale[inner].mean() < scale[outer].mean() - 0.02


# -- markers move with the material -------------------------------------------------------------

def test_uniform_shift_moves_markers_by_its_size_in_pixels(none_renderer):
    rest = none_renderer.render(np.zeros((33, 33, 3)))["truth"]
    moved = np.zeros((33, 33, 3), np.float32)
    moved[..., 0] = 0.5                                    # 0.5 mm = 3.2 px at 128 px / 20 mm
    _, motion = matched_motion(rest, none_renderer.render(moved)["truth"])
    inside = motion[np.abs(motion[:, 0] - 3.2) < 1.5]
    assert len(inside) >= 70                               # the last column may leave the frame
    assert inside[:, 0].mean() == pytest.approx(3.2, abs=0.3)
    assert np.abs(inside[:, 1]).mean() < 0.3


def test_view_mm_frames_the_pad_centre(none_renderer):
    """view_mm [10, 10] of the 20 mm flat pad: the frame shows the central half, so markers
    lie twice as far apart and twice as far from the centre, a shift moves them twice as many
    pixels, and the attrs record the view; a bad view_mm is named."""
    gx, gy, z, on = flat_pad()
    half = Renderer(gx, gy, z, on, pattern("Array3"), look="none", size=(128, 128), spp=1,
                    view_mm=[10.0, 10.0])
    assert half.distance == pytest.approx(none_renderer.distance / 2)
    whole, near = (centroids(r.render(np.zeros((33, 33, 3)))["truth"]) - 63.5
                   for r in (none_renderer, half))
    spacing = [np.median(np.sort(np.linalg.norm(c[:, None] - c[None], axis=-1), 1)[:, 1])
               for c in (whole, near)]
    assert spacing[1] / spacing[0] == pytest.approx(2.0, rel=0.03)
    inner = whole[np.abs(whole).max(1) < 28]                   # the markers still in the view
    matched = near[np.linalg.norm(2 * inner[:, None] - near[None], axis=-1).argmin(1)]
    assert len(inner) >= 9 and np.abs(matched - 2 * inner).max() < 1.0
    moved = np.zeros((33, 33, 3), np.float32)
    moved[..., 0] = 0.5                                        # 0.5 mm = 6.4 px at 128 px / 10 mm
    _, motion = matched_motion(half.render(np.zeros((33, 33, 3)))["truth"],
                               half.render(moved)["truth"])
    inside = motion[np.abs(motion[:, 0] - 6.4) < 2.0]
    assert len(inside) >= 10 and inside[:, 0].mean() == pytest.approx(6.4, abs=0.4)
    deform = _deform(2, grid=33)
    _, final = drain(render_sequence(deform=deform, patterns=_patterns("Array3", pattern("Array3")),
                                     skin="Array3", spec={"sensor": "sim", "pattern": "Array3",
                                                          "look": "none", "view_mm": [10, 10]},
                                     size=[32, 32], spp=1, backend="auto"))
    assert final["attrs"]["view_mm"] == [10.0, 10.0]
    for bad in ([10.0], [10.0, -1.0], "wide", [10.0, float("nan")]):
        with pytest.raises(ValueError, match=r"render view_mm .*two positive lengths"):
            Renderer(gx, gy, z, on, pattern("Array3"), view_mm=bad, backend="scalar")


def test_indenter_shift_moves_markers_to_plus_column(none_renderer):
    gx, gy, _, _ = flat_pad()
    pressed = press(gx, gy, depth=1.0)
    sheared = press(gx, gy, depth=1.0, shear=(0.8, 0.0))
    start, motion = matched_motion(none_renderer.render(pressed)["truth"],
                                   none_renderer.render(sheared)["truth"])
    near = np.hypot(*(start - 63.5).T) < 20                # within ~3 mm of the contact
    assert near.sum() >= 4
    assert np.all(motion[near, 0] > 1.5)                   # +x -> +column, several pixels
    assert np.abs(motion[near, 1]).mean() < 0.5 * motion[near, 0].mean()


def test_press_moves_markers_radially_outward(none_renderer):
    gx, gy, _, _ = flat_pad()
    centre_mm = np.array([3.0, -2.0])                     # off-axis: not the image centre
    rest = none_renderer.render(np.zeros((33, 33, 3)))["truth"]
    start, motion = matched_motion(rest, none_renderer.render(press(gx, gy, centre_mm, depth=1.2))["truth"])
    centre_px = (centre_mm + 10) * 128 / 20 - 0.5
    radial = start - centre_px
    dist = np.linalg.norm(radial, axis=1)
    ring = (dist > 5) & (dist < 30)
    assert ring.sum() >= 8
    outward = (motion[ring] * radial[ring]).sum(1) / dist[ring]
    assert np.mean(outward > 0) >= 0.9 and outward.mean() > 0.5
    far = dist > 60
    assert np.abs(motion[far]).max() < 0.5                 # the pad far away stays put


# -- looks ---------------------------------------------------------------------------------------

def test_golden_gelsight_frame():
    out = golden_render()
    raw = cv2.imread(str(GOLDEN / "gelsight_c2_64.png"))[..., ::-1]
    truth = cv2.imread(str(GOLDEN / "gelsight_c2_64_truth.png"), cv2.IMREAD_GRAYSCALE)
    assert out["raw"].shape == (1, 64, 64, 3) and out["truth"].shape == (1, 64, 64)
    assert np.abs(out["raw"][0].astype(float) - raw).mean() < 2.0
    assert (out["truth"][0] == truth).mean() >= 0.99


def test_gelsight_indentation_tints_the_contact_and_noise_is_seeded(gelsight_frame):
    gx, gy, z, on, d = gelsight_frame
    r = Renderer(gx, gy, z, on, gelsight_pattern("A-II"), look="gelsight", size=(64, 64), spp=1)
    rest, pressed = r.render(np.zeros_like(d))["raw"], r.render(d)["raw"]
    change = np.abs(pressed.astype(float) - rest).sum(-1)
    col, row = (np.array([2.0, -1.0]) + 12.5) * 64 / 25
    yy, xx = np.mgrid[:64, :64]
    dist = np.hypot(xx - col, yy - row)
    assert change[dist < 8].mean() > 20 and change[dist > 24].mean() < 3
    # three coloured LEDs from three sides: the gel is tinted, differently across the pad
    assert np.ptp(rest.astype(float), axis=-1).mean() > 20 and (rest == 255).mean() < 0.01
    assert np.argmax(rest[2, 32]) == 0 and np.argmax(rest[60, 8]) == 2 and np.argmax(rest[60, 56]) == 1
    other = Renderer(gx, gy, z, on, gelsight_pattern("A-II"), look="gelsight", size=(64, 64), spp=1,
                     light=[[0.1, 0.1, 0.7], [0.7, 0.3, 0.1], [0.2, 0.6, 0.6]])
    assert np.abs(other.render(d)["raw"].astype(float) - pressed).mean() > 10
    # automatic exposure: LED strengths are relative, three times brighter LEDs = same image
    bright = Renderer(gx, gy, z, on, gelsight_pattern("A-II"), look="gelsight", size=(64, 64), spp=1,
                      light=3 * np.asarray(LOOKS["gelsight"].light))
    assert np.abs(bright.render(d)["raw"].astype(float) - pressed).max() <= 1
    # camera noise: sigma in grey levels, reproducible per frame index, different across frames
    noisy = Renderer(gx, gy, z, on, gelsight_pattern("A-II"), look="gelsight", size=(64, 64), spp=1,
                     noise=4.0, seed=3)
    a, b, c = noisy.render(d, 5)["raw"], noisy.render(d, 5)["raw"], noisy.render(d, 6)["raw"]
    assert np.array_equal(a, b) and not np.array_equal(a, c)
    assert np.std(a.astype(float) - pressed) == pytest.approx(4.0, rel=0.15)
    assert np.array_equal(noisy.render(d, 5)["truth"], r.render(d)["truth"])   # truth has no noise


def test_truth_follows_the_markers_in_the_raw_image(gelsight_frame):
    """The truth mask marks the dark dots of the camera image of the same frame."""
    gx, gy, z, on, d = gelsight_frame
    r = Renderer(gx, gy, z, on, gelsight_pattern("D-I"), look="gelsight", size=(96, 96), spp=4)
    out = r.render(d)
    grey, marker = out["raw"].mean(-1), out["truth"] > 0
    assert len(centroids(out["truth"])) == 56
    assert grey[marker].mean() < 0.5 * grey[~marker].mean()


@pytest.mark.skipif(not llvm_usable(), reason="Dr.Jit's LLVM backend is unusable here "
                    "(no libLLVM >= 17, or the probe render failed)")
def test_llvm_and_scalar_agree():
    llvm, scalar = golden_render("llvm"), golden_render("scalar")
    assert np.abs(llvm["raw"].astype(float) - scalar["raw"]).mean() < 1.0
    assert (llvm["truth"] == scalar["truth"]).mean() >= 0.995


# -- backend and arguments -----------------------------------------------------------------------

def test_backend_choice():
    assert llvm_version("/usr/lib/x86_64-linux-gnu/libLLVM-19.so") == 19
    assert llvm_version("libLLVM.so.19.1") == 19 and llvm_version("libLLVM-14.0.6.so.1") == 14
    assert resolve_backend("scalar") == "scalar"
    assert resolve_backend("auto") == ("llvm" if llvm_usable() else "scalar")
    with pytest.raises(ValueError, match="backend"):
        resolve_backend("cuda")


def test_bad_arguments_raise():
    gx, gy, z, on = flat_pad(9)
    with pytest.raises(ValueError, match="spp"):
        Renderer(gx, gy, z, on, pattern("Array3"), spp=2, backend="scalar")
    with pytest.raises(ValueError, match="look"):
        Renderer(gx, gy, z, on, pattern("Array3"), look="taxel", backend="scalar")
    with pytest.raises(ValueError, match="light"):
        Renderer(gx, gy, z, on, pattern("Array3"), look="gelsight", light=[1, 0, 0], backend="scalar")


# -- node -----------------------------------------------------------------------------------------

def _deform(n, grid=17, pad=20.0):
    gx, gy, z, on = flat_pad(grid, pad)
    rng = np.random.default_rng(0)
    depth = np.linspace(0, 1.5, n)
    disp = np.stack([press(gx, gy, depth=float(k)) for k in depth])
    labels = {"force": rng.normal(size=(n, 3)).astype(np.float32), "depth": depth,
              "normalised_depth": (depth / 1.5).astype(np.float32), "position": rng.normal(size=(n, 3)),
              "shift": rng.normal(size=(n, 2)), "phase": (np.arange(n) % 4).astype(np.int8),
              "contact_id": (np.arange(n) // 10).astype(np.int32),
              "indenter_id": np.full(n, 3, np.int16), "paired": np.arange(n) % 3 == 0,
              "frame": np.arange(100, 100 + n, dtype=np.int64)}
    return {"grid_x": gx, "grid_y": gy, "surface_z": z, "on_pad": on, "displacement": disp, **labels}


def _patterns(name, ms):
    return {"markers": {name: {"centers": ms.centers, "axes": ms.axes, "angles": ms.angles,
                               "pad_size_mm": np.asarray(ms.pad_size_mm)}}}


def test_node_streams_chunks_and_carries_labels():
    import drjit as dr
    threads = dr.thread_count()
    deform = _deform(40)
    gen = render_sequence(deform=deform, patterns=_patterns("Array3", pattern("Array3")),
                          skin="Array3", spec={"sensor": "sim", "pattern": "Array3", "look": "none",
                                               "source": "render"},
                          size=[32, 32], spp=1, backend="auto")
    assert inspect.isgenerator(gen)
    chunks, final = drain(gen)
    assert [len(c["truth"]) for c in chunks] == [32, 8]
    assert all("raw" not in c for c in chunks)
    truth = np.concatenate([c["truth"] for c in chunks])
    assert truth.shape == (40, 32, 32) and truth.dtype == np.uint8
    for key in (k for k in LABEL_KEYS if k in deform):          # the labels the deformation has
        got = np.concatenate([c[key] for c in chunks])
        assert got.dtype == deform[key].dtype and np.array_equal(got, deform[key]), key
    assert np.array_equal(final["truth_reference"], truth[0])           # frame 0 is at rest
    assert not np.array_equal(truth[-1], truth[0])
    assert bytes(final["figures"]["frames"][:8]) == PNG
    attrs = final["attrs"]
    assert attrs["look"] == "none" and attrs["pattern"] == "Array3" and attrs["sensor"] == "sim"
    assert attrs["size"] == [32, 32] and attrs["spp"] == 1 and attrs["backend"] in ("llvm", "scalar")
    assert final["timing"]["seconds_per_frame"] > 0 and "seconds_per_frame" not in attrs
    assert dr.thread_count() == threads                                 # restored after the node


def test_node_camera_look_outputs_raw_and_references():
    ms = gelsight_pattern("A-I", seed=7)
    flat = {f"markers/gelsight-A-I/{k}": v for k, v in _patterns("x", ms)["markers"]["x"].items()}
    deform = _deform(3, pad=25.0)
    spec = {"sensor": "gelsight-A-I", "pattern": "gelsight-A-I", "look": "gelsight", "noise": 2.0,
            "light": [[0.7, 0.1, 0.1], [0.1, 0.7, 0.1], [0.1, 0.1, 0.7]]}
    gen = render_sequence(deform=deform, patterns=flat, skin="gelsight-A-I", spec=spec,
                          size=[48, 40], spp=1, backend="auto")
    chunks, final = drain(gen)
    assert chunks[0]["raw"].shape == (3, 48, 40, 3) and chunks[0]["truth"].shape == (3, 48, 40)
    assert final["raw_reference"].shape == (48, 40, 3) and final["truth_reference"].shape == (48, 40)
    assert np.array_equal(final["truth_reference"], chunks[0]["truth"][0])
    assert final["attrs"]["noise"] == 2.0
    again, _ = drain(render_sequence(deform=deform, patterns=flat, skin="gelsight-A-I", spec=spec,
                                     size=[48, 40], spp=1, backend="auto"))
    assert np.array_equal(again[0]["raw"], chunks[0]["raw"])             # seeded noise
    with pytest.raises(InputError, match=r"pattern 'Array9' is not drawn \(.*gelsight-A-I"):
        next(render_sequence(deform=deform, patterns=flat, skin="s", spec={**spec, "pattern": "Array9"},
                             size=[8, 8], spp=1, backend="auto"))
    assert marker_set(flat, "gelsight-A-I").pad_size_mm == (25.0, 25.0)


if __name__ == "__main__":
    out = golden_render("scalar")
    cv2.imwrite(str(GOLDEN / "gelsight_c2_64.png"), out["raw"][0][..., ::-1])
    cv2.imwrite(str(GOLDEN / "gelsight_c2_64_truth.png"), out["truth"][0])
    print("wrote", GOLDEN / "gelsight_c2_64.png", GOLDEN / "gelsight_c2_64_truth.png")
