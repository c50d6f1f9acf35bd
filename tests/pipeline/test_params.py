"""params.yaml is the schema: overlays and overrides may change values, never invent keys."""
import pytest

from pipeline import params as P
from pipeline.errors import PipelineError

BASE = """\
seed: 1
lr: 0.01
name: sim
flag: false
sizes: [64, 128]
sensors:
  gelsight:
    E: 1.45e5
    markers: 56
"""


@pytest.fixture
def base(tmp_path):
    f = tmp_path / "params.yaml"
    f.write_text(BASE)
    (tmp_path / "params").mkdir()
    return f


def overlay(base, text, name="ci"):
    (base.parent / "params" / f"{name}.yaml").write_text(text)
    return name


def test_profile_and_overrides_apply_in_order(base):
    name = overlay(base, "seed: 2\nsensors:\n  gelsight:\n    markers: 60\n")
    p = P.load(base, name, ["seed=3", "lr=1", "sizes=[8, 16]"])
    assert p["seed"] == 3 and p["lr"] == 1.0 and isinstance(p["lr"], float)
    assert p["sensors"]["gelsight"] == {"E": 1.45e5, "markers": 60}
    assert p["sizes"] == [8, 16]


@pytest.mark.parametrize("text,message", [
    ("seeds: 2\n", r"unknown param 'seeds' \(.*ci.yaml:1\); did you mean 'seed'\?"),
    ("sensors:\n  gelsight:\n    Ee: 1.0\n", r"unknown param 'sensors.gelsight.Ee' \(.*ci.yaml:3\)"),
    ("seed: 2.5\n", r"param 'seed' \(.*ci.yaml:1\) must be int, got float 2.5"),
    ("flag: 1\n", r"param 'flag' \(.*ci.yaml:1\) must be bool, got int 1"),
    ("sizes: [1, x]\n", r"param 'sizes\[1\]' \(.*ci.yaml:1\) must be int, got str 'x'"),
    ("seed: [1\nlr: 2\n", r"malformed YAML in .*ci.yaml:2"),
    ("- a\n- b\n", r"must hold a mapping"),
    ("seed: 2\nlr: 0.1\nseed: 3\n", r"duplicate param 'seed' in .*ci.yaml:3 \(first at line 1\)"),
])
def test_profile_errors_name_key_and_line(base, text, message):
    name = overlay(base, text)
    with pytest.raises(PipelineError, match=message):
        P.load(base, name)


@pytest.mark.parametrize("override,message", [
    ("sed=1", r"unknown param 'sed' \(-p sed=1\); did you mean 'seed'\?"),
    ("seed=abc", r"param 'seed' \(-p seed=abc\) must be int, got str 'abc'"),
    ("name=3", r"param 'name' .* must be str, got int 3"),
    ("sensors.tactip.E=1", r"unknown param 'sensors.tactip.E'"),
    ("seed", r"malformed override 'seed': expected KEY=VALUE"),
    ("lr=[1", r"malformed value in override 'lr=\[1'"),
    ("sensors.gelsight={E: 1, x: 2}", r"unknown param 'sensors.gelsight.x'"),
])
def test_override_errors(base, override, message):
    with pytest.raises(PipelineError, match=message):
        P.load(base, None, [override])


def test_non_utf8_profile(base):
    (base.parent / "params" / "bin.yaml").write_bytes(b"\xff\xfeseed: 1\n")
    with pytest.raises(PipelineError, match=r"bin.yaml is not UTF-8 text \(byte 0\)"):
        P.load(base, "bin")


def test_untyped_param_accepts_plain_values_only(tmp_path):
    f = tmp_path / "params.yaml"
    f.write_text("extra: null\n")
    assert P.load(f, None, ["extra=[1, a]"])["extra"] == [1, "a"]
    with pytest.raises(PipelineError, match=r"param 'extra' .* must be a number, string, bool, list or mapping, got date"):
        P.load(f, None, ["extra=2020-01-01"])


def test_unknown_profile_lists_known(base):
    overlay(base, "seed: 2\n", "paper")
    with pytest.raises(PipelineError, match=r"unknown profile 'nope' \(known: default, paper\)"):
        P.load(base, "nope")


def test_extends_resolves_after_the_profile_and_overrides(tmp_path):
    """An entry with `extends` is its sibling deep-merged with its own keys, resolved after the
    profile and -p overrides, so a change to the base reaches every entry that extends it."""
    f = tmp_path / "params.yaml"
    f.write_text("sensors:\n"
                 "  base: {grid: [65, 65], look: {kind: gel, noise: 3.0}, material: r10}\n"
                 "  mid: {extends: base, material: r6}\n"
                 "  leaf: {extends: mid, look: {noise: 1.0}}\n")
    (tmp_path / "params").mkdir()
    (tmp_path / "params" / "ci.yaml").write_text("sensors:\n  base: {grid: [33, 33]}\n")
    p = P.load(f, "ci", ["sensors.leaf.material=r18"])
    assert p["sensors"]["mid"] == {"grid": [33, 33], "look": {"kind": "gel", "noise": 3.0}, "material": "r6"}
    assert p["sensors"]["leaf"] == {"grid": [33, 33], "look": {"kind": "gel", "noise": 1.0}, "material": "r18"}
    assert p["sensors"]["base"] == {"grid": [33, 33], "look": {"kind": "gel", "noise": 3.0}, "material": "r10"}
    f.write_text("sensors:\n  a: {extends: b, x: 1}\n  b: {extends: a, x: 2}\n")
    with pytest.raises(PipelineError, match=r"param 'sensors.b.extends': entries extend each other in a loop "
                                             r"\(a -> b -> a\)"):
        P.load(f)
    f.write_text("sensors:\n  a: {extends: nosuch, x: 1}\n  b: {x: 2}\n")
    with pytest.raises(PipelineError, match=r"param 'sensors.a.extends' names 'nosuch', not an entry beside it \(b\)"):
        P.load(f)
