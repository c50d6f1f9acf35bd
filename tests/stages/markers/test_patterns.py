"""Tests for the reference marker patterns (counts/areas from FACTS)."""
import hashlib
from pathlib import Path

import cv2
import numpy as np
import pytest

from stages.markers.patterns import (
    PATTERNS, MarkerSet, gelsight_pattern, marker_texture, pattern, rasterize,
    tactip_pattern, uskin_pattern,
)

# FACTS, "The 12 reference marker patterns": name -> (markers, marker area px at 568x568)
FACTS = {
    "Array1": (225, 114), "Array2": (100, 223), "Array3": (80, 362), "Array4": (99, 302),
    "Circle1": (320, 115), "Circle2": (115, 222), "Circle3": (111, 363), "Circle4": (124, 246),
    "Diamond1": (245, 115), "Diamond2": (103, 218), "Diamond3": (81, 365), "Diamond4": (81, 251),
}
GOLDEN = Path(__file__).parent / "golden" / "array2_128.png"
ARRAY2_128_SHA256 = "19f7749329d8b0cf5481e424427cbeabe1de904426bace12cd81fbaf730661dd"
REGEN = ("if the pattern code changed on purpose, regenerate with: python -c \"import cv2; "
         "from stages.markers.patterns import pattern, rasterize; cv2.imwrite("
         "'tests/stages/markers/golden/array2_128.png', rasterize(pattern('Array2'), "
         "size=(128, 128)))\" and update ARRAY2_128_SHA256 to the sha256 of the image bytes")


def _components(img):
    n, _, stats, _ = cv2.connectedComponentsWithStats(img, connectivity=8)
    return n - 1, stats[1:, cv2.CC_STAT_AREA]


def _assert_no_overlap(ms):
    d = np.linalg.norm(ms.centers[:, None] - ms.centers[None], axis=-1)
    a = ms.axes.max(1)
    np.fill_diagonal(d, np.inf)
    assert np.all(d > a[:, None] + a[None, :])


def _rigid_fit(src, dst):
    """Least-squares rotation + shift with dst ~ src @ R.T + t (Kabsch, 2-D)."""
    mu_s, mu_d = src.mean(0), dst.mean(0)
    u, _, vt = np.linalg.svd((src - mu_s).T @ (dst - mu_d))
    rot = (u @ vt).T
    ang = np.arctan2(rot[1, 0], rot[0, 0])
    return ang, mu_d - mu_s @ rot.T, rot


def test_pattern_names_in_facts_order():
    assert PATTERNS == tuple(FACTS)


@pytest.mark.parametrize("name", PATTERNS)
def test_counts_areas_and_geometry(name):
    count, area = FACTS[name]
    ms = pattern(name)
    assert isinstance(ms, MarkerSet)
    assert len(ms) == count
    assert ms.centers.shape == (count, 2) and ms.axes.shape == (count, 2)
    assert ms.angles.shape == (count,) and ms.pad_size_mm == (20.0, 20.0)

    img = rasterize(ms, size=(568, 568))
    assert img.dtype == np.uint8 and set(np.unique(img)) <= {0, 255}
    n_cc, areas = _components(img)
    assert n_cc == count
    assert abs(areas.mean() / area - 1) < 0.10, (areas.mean(), area)

    _assert_no_overlap(ms)
    half = np.array(ms.pad_size_mm) / 2
    margin = 0.25
    assert np.all(np.abs(ms.centers) + ms.axes.max(1)[:, None] <= half - margin)


@pytest.mark.parametrize("name", ["Array1", "Circle4", "Diamond1"])
def test_seeded_variant_is_small_rigid_motion_inside_pad(name):
    ref, var = pattern(name), pattern(name, seed=7)
    ang, t, _ = _rigid_fit(ref.centers, var.centers)
    assert 0 < abs(np.rad2deg(ang)) <= 3.0 and 0 < np.linalg.norm(t) <= 0.3
    assert np.all(np.abs(var.centers) + var.axes.max(1)[:, None] <= 10.0 - 0.25)
    assert _components(rasterize(var, size=(568, 568)))[0] == len(ref)


def test_pad_size_scales_geometry_not_image():
    a = rasterize(pattern("Circle2"), size=(256, 256))
    b = rasterize(pattern("Circle2", pad_size_mm=(25, 25)), size=(256, 256))
    assert np.array_equal(a, b)
    np.testing.assert_allclose(pattern("Circle2", pad_size_mm=(25, 25)).centers,
                               pattern("Circle2").centers * 1.25)


def test_unknown_names_raise():
    with pytest.raises(KeyError):
        pattern("Array5")
    with pytest.raises(KeyError):
        gelsight_pattern("B-I")


@pytest.mark.parametrize("base,twin", [("A-II", "A-I"), ("C-II", "C-I")])
def test_gelsight_twin_is_small_rigid_shift_and_rotation(base, twin):
    ref, var = gelsight_pattern(base), gelsight_pattern(twin, seed=3)
    assert len(ref) == len(var) == 56
    ang, t, rot = _rigid_fit(ref.centers, var.centers)
    resid = var.centers - (ref.centers @ rot.T + t)
    assert np.abs(resid).max() < 1e-9               # purely rigid
    assert 0 < abs(np.rad2deg(ang)) <= 3.0 + 1e-9
    assert 0 < np.linalg.norm(t) <= 0.3 + 1e-9
    np.testing.assert_allclose(var.angles - ref.angles, ang)
    # deterministic in the seed, different across seeds
    assert np.array_equal(var.centers, gelsight_pattern(twin, seed=3).centers)
    assert not np.allclose(var.centers, gelsight_pattern(twin, seed=4).centers)
    # the -II twins do not depend on the seed
    assert np.array_equal(ref.centers, gelsight_pattern(base, seed=9).centers)


@pytest.mark.parametrize("twin", ["A-I", "A-II", "C-I", "C-II", "D-I"])
def test_gelsight_layouts_valid(twin):
    ms = gelsight_pattern(twin, seed=1)
    assert ms.pad_size_mm == (25.0, 25.0) and len(ms) == 56
    _assert_no_overlap(ms)
    assert np.all(np.abs(ms.centers) + ms.axes.max(1)[:, None] <= 12.5 - 0.5)
    assert _components(rasterize(ms, size=(256, 256)))[0] == 56


def test_tactip_127_pins_in_dome_footprint():
    ms = tactip_pattern()
    assert len(ms) == 127 and ms.pad_size_mm == (40.0, 40.0)
    _assert_no_overlap(ms)
    assert np.all(np.hypot(*ms.centers.T) + ms.axes.max(1) < 20.0)
    assert _components(rasterize(ms, size=(400, 400)))[0] == 127
    # projection of the dome crowds pins towards the rim: outer spacing < inner
    r = np.hypot(*ms.centers.T)
    d = np.linalg.norm(ms.centers[:, None] - ms.centers[None], axis=-1)
    np.fill_diagonal(d, np.inf)
    nn = d.min(1)
    assert nn[r > 0.8 * r.max()].mean() < nn[r < 0.3 * r.max()].mean()


def test_uskin_4x4_grid():
    ms = uskin_pattern()
    assert len(ms) == 16 and ms.pad_size_mm == (24.6, 22.6)
    assert len(np.unique(np.round(ms.centers[:, 0], 6))) == 4
    assert len(np.unique(np.round(ms.centers[:, 1], 6))) == 4
    _assert_no_overlap(ms)
    assert _components(rasterize(ms, size=(480, 640)))[0] == 16


def test_texture_is_coverage_and_thresholds_to_raster():
    ms = pattern("Circle4")
    tex = marker_texture(ms, size=(200, 200))
    assert tex.dtype == np.float32 and tex.shape == (200, 200)
    assert tex.min() == 0.0 and tex.max() == 1.0
    assert 0 < np.count_nonzero((tex > 0) & (tex < 1))          # antialiased edges
    assert np.array_equal(rasterize(ms, size=(200, 200)), np.where(tex >= 0.5, 255, 0))


def test_rasterize_non_square_size():
    img = rasterize(pattern("Array2"), size=(480, 640))
    assert img.shape == (480, 640)
    assert _components(img)[0] == 100


def test_golden_array2_digest_and_png():
    img = rasterize(pattern("Array2"), size=(128, 128))
    assert hashlib.sha256(img.tobytes()).hexdigest() == ARRAY2_128_SHA256, REGEN
    golden = cv2.imread(str(GOLDEN), cv2.IMREAD_GRAYSCALE)
    assert golden is not None, f"missing {GOLDEN}; {REGEN}"
    assert np.array_equal(img, golden), REGEN


@pytest.mark.parametrize("size", [[96], [96, 20], [96.0, 96]])
def test_reference_set_rejects_an_unusable_image_size(size):
    from stages.common import InputError
    from stages.markers.patterns import reference_set
    with pytest.raises(InputError, match=r"patterns.image_size must be \[height, width\] in pixels, each >= 32"):
        reference_set(["Array1"], size=size)
