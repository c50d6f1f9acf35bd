"""scripts/shear_cue.py: the shear cue of taxel images, on dots drawn with a known response."""
import numpy as np
import pytest

from tests.helpers import load_script

SIZE = 64
CENTRES = [(8 + 16 * r, 8 + 16 * c) for r in range(4) for c in range(4)]


@pytest.fixture(scope="module")
def shear_cue():
    return load_script("shear_cue")


def draw(shift=0, left=1, right=1):
    """16 square dots: radius 1 at rest; `left`/`right` the radius of the dots in the left /
    right two columns; `shift` moves every dot right by that many px."""
    im = np.zeros((SIZE, SIZE), np.uint8)
    for i, (y, x) in enumerate(CENTRES):
        r = left if i % 4 < 2 else right
        im[y - r:y + r + 1, x + shift - r:x + shift + r + 1] = 255
    return im


def artifact(frames, fx):
    n = len(frames)
    force = np.zeros((n, 3))
    force[:, 0] = fx
    return {"reference": draw(), "images": np.stack(frames), "force": force,
            "contact_id": np.repeat(np.arange(n // 5), 5)}


FX = np.tile([-2.0, -1.0, 0.0, 1.0, 2.0], 4)


def test_dots_that_move_with_the_shear(shear_cue):
    # 3-axis-like: every dot grows to radius 3 and moves fx px: the growth follows the shear
    art = artifact([draw(int(f), 3, 3) for f in FX], FX)
    c = shear_cue.cue(art)
    assert c["frames"] == 20
    assert c["corr_x"] > 0.95
    assert c["dot_move_px_per_N"] == pytest.approx(1.0, abs=0.02)


def test_dots_that_grow_behind_the_shear(shear_cue):
    # z-only-like: dots stay put; the dots behind the shear (left for fx > 0) grow more
    frames = [draw(0, 3 + int(f > 0) * int(f), 3 + int(f < 0) * int(-f)) for f in FX]
    c = shear_cue.cue(artifact(frames, FX))
    assert c["corr_x"] < -0.9
    assert abs(c["dot_move_px_per_N"]) < 1e-6


def test_dots_that_shrink_ahead_of_the_shear(shear_cue):
    # z-only with min_area < base_area: the dots ahead of the shear shrink below their rest size
    # (right for fx > 0) while those behind grow; the rest frame shrinks nothing
    frames = [draw(0, 1 + int(f > 0), 1 - int(f > 0)) if f > 0 else
              draw(0, 1 - int(f < 0), 1 + int(f < 0)) for f in FX]
    c = shear_cue.cue(artifact(frames, FX))
    assert c["shrink_frames"] == 16                       # 4 sheared frames of each contact
    assert c["shrink_x"] > 0.9 and c["corr_x"] < -0.9
    unshrunk = shear_cue.cue(artifact([draw(int(f), 3, 3) for f in FX], FX))
    assert unshrunk["shrink_frames"] == 0 and np.isnan(unshrunk["shrink_x"])


def test_an_unknown_store_entry_is_one_line(shear_cue, tmp_path):
    with pytest.raises(SystemExit, match=r"shear_cue: .*markers\[skin=uskin-z\] is not built"):
        shear_cue.main(["--store", str(tmp_path), "--source", "nowhere"])
