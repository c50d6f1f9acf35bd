"""Cache keys and content digests are pinned: a key must never change by accident."""
import numpy as np
import pytest

from pipeline.hashing import ContentDigest, cache_key, canonical


def test_canonical_is_order_and_spelling_independent():
    assert canonical({"b": 1, "a": [1.0, 2.5]}) == canonical({"a": [1, 2.5], "b": 1.0}) == '{"a":[1,2.5],"b":1}'
    assert canonical({"x": np.float32(0.5), "y": np.arange(3)}) == '{"x":0.5,"y":[0,1,2]}'
    assert canonical(True) != canonical(1)


def test_cache_key_pinned():
    key = cache_key("render[sensor=gelsight-a2]", "0123456789abcdef",
                    {"params": {"size": 64, "spp": 4}, "grid": {"sensor": "gelsight-a2"}},
                    {"surface": "ab" * 32})
    assert key == "a6eccdfe0b71a30bc13ecaf8e921fa2c"  # ENGINE_VERSION 2


def test_cache_key_changes_with_each_part():
    base = ("n", "c", {"a": 1}, {"i": "d"})
    k0 = cache_key(*base)
    assert cache_key("m", *base[1:]) != k0
    assert cache_key("n", "c2", {"a": 1}, {"i": "d"}) != k0
    assert cache_key("n", "c", {"a": 2}, {"i": "d"}) != k0
    assert cache_key("n", "c", {"a": 1}, {"i": "e"}) != k0


def test_content_digest_pinned_and_chunking_invariant():
    x = np.arange(24, dtype=np.float32).reshape(6, 2, 2)
    whole = ContentDigest()
    whole.update_whole("x", x)
    whole.update_whole("names", np.array(["a", "bc"], dtype=object))
    chunked = ContentDigest()
    for i in range(0, 6, 4):
        chunked.update("x", np.ascontiguousarray(x[i:i + 4]), dtype=x.dtype.str, shape_tail=(2, 2))
    chunked.update_whole("names", np.array(["a", "bc"], dtype=object))
    attrs = {"attrs": {"unit": "mm"}, "metrics": {}}
    assert whole.hexdigest(attrs) == chunked.hexdigest(attrs)
    assert whole.hexdigest(attrs) == "dd78e872b7e658d45413faa0b44f319db3bdae90318d4e4ccc5c2e4649847ab9"


@pytest.mark.parametrize("change", ["dtype", "shape", "value", "attr"])
def test_content_digest_sees_every_change(change):
    x = np.arange(6, dtype=np.int32).reshape(2, 3)
    attrs = {"attrs": {"unit": "mm"}}
    d0 = ContentDigest()
    d0.update_whole("x", x)
    y, a = x, attrs
    if change == "dtype":
        y = x.astype(np.uint32)
    elif change == "shape":
        y = x.reshape(3, 2)
    elif change == "value":
        y = x.copy()
        y[1, 2] = 7
    else:
        a = {"attrs": {"unit": "m"}}
    d1 = ContentDigest()
    d1.update_whole("x", y)
    assert d0.hexdigest(attrs) != d1.hexdigest(a)
