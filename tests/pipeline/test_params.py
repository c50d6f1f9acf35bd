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


# -- ranges: the values a param may take, one file, checked before anything runs -------------

RANGED = """\
steps: 100
spp: 4
size: [64, 64]
seed_ref: null
sensors:
  a: &pad {spacing_mm: 0.5, material: soft}
  b: {<<: *pad, material: hard}
materials: {soft: {E: 1.0}, hard: {E: 2.0}}
"""

RANGES = """\
steps: {ge: 1, le: 1000}
spp: {one_of: [1, 4, 9]}
size: {len: 2, items: {ge: 16, le: 512, multiple_of: 8}}
seed_ref: {ge: 0, whole: true, nullable: true}
sensors.*.spacing_mm: {gt: 0}
sensors.*.material: {key_of: materials}
"""


@pytest.fixture
def ranged(tmp_path):
    f = tmp_path / "params.yaml"
    f.write_text(RANGED)
    (tmp_path / "params").mkdir()
    (tmp_path / "params" / "ci.yaml").write_text("steps: 10\nsensors:\n  b: {spacing_mm: 0.0}\n")
    (tmp_path / "ranges.yaml").write_text(RANGES)
    return f


def _load(ranged, profile=None, *overrides):
    return P.load(ranged, profile, list(overrides), None, ranged.parent / "ranges.yaml")


@pytest.mark.parametrize("override,message", [
    ("steps=-5", "param 'steps' = -5 (-p steps=-5) must be >= 1 (range 'steps' in {r}:1)"),
    ("steps=100000000000000000000", "param 'steps' = 100000000000000000000 (-p steps=100000000000000000000) "
                                    "must be <= 1000 (range 'steps' in {r}:1)"),
    ("spp=2", "param 'spp' = 2 (-p spp=2) must be one of 1, 4, 9 (range 'spp' in {r}:2)"),
    ("size=[64]", "param 'size' = [64] (-p size=[64]) must have 2 items, has 1 (range 'size' in {r}:3)"),
    ("size=[64, 100]", "param 'size[1]' = 100 (-p size=[64, 100]) must be a multiple of 8 (range 'size' in {r}:3)"),
    ("size=[64, 100000]", "param 'size[1]' = 100000 (-p size=[64, 100000]) must be <= 512 (range 'size' in {r}:3)"),
    ("seed_ref=-1", "param 'seed_ref' = -1 (-p seed_ref=-1) must be >= 0 (range 'seed_ref' in {r}:4)"),
    ("seed_ref=1.5", "param 'seed_ref' = 1.5 (-p seed_ref=1.5) must be a whole number (range 'seed_ref' in {r}:4)"),
    ("sensors.a.spacing_mm=0", "param 'sensors.a.spacing_mm' = 0.0 (-p sensors.a.spacing_mm=0) must be > 0 "
                               "(range 'sensors.*.spacing_mm' in {r}:5)"),
    ("sensors.a={spacing_mm: -1}", "param 'sensors.a.spacing_mm' = -1.0 (-p sensors.a={spacing_mm: -1}) "
                                   "must be > 0 (range 'sensors.*.spacing_mm' in {r}:5)"),
    ("sensors.b.material=rubber", "param 'sensors.b.material' = 'rubber' (-p sensors.b.material=rubber) must "
                                  "name an entry of materials (range 'sensors.*.material' in {r}:6)"),
])
def test_a_value_out_of_range_is_one_line_naming_key_value_rule_and_origin(ranged, override, message):
    with pytest.raises(PipelineError) as err:
        _load(ranged, None, override)
    assert str(err.value) == message.replace("{r}", str(ranged.parent / "ranges.yaml"))


def test_a_value_from_a_profile_or_inherited_through_a_merge_key_names_its_line(ranged):
    with pytest.raises(PipelineError, match=r"^param 'sensors\.b\.spacing_mm' = 0\.0 \(.*/params/ci\.yaml:3\) "
                                            r"must be > 0 \(range 'sensors\.\*\.spacing_mm' in .*ranges\.yaml:5\)$"):
        _load(ranged, "ci")
    # the base value b inherits from a (`<<: *pad`) is named by b's own line
    ranged.write_text(RANGED.replace("spacing_mm: 0.5", "spacing_mm: -0.5"))
    with pytest.raises(PipelineError, match=r"^param 'sensors\.a\.spacing_mm' = -0\.5 \(.*params\.yaml:6\)"):
        _load(ranged)
    ranged.write_text(RANGED.replace("b: {<<: *pad, material: hard}", "b: {<<: *pad, material: hard}\n  c: {<<: *pad}"))
    assert _load(ranged, None, "sensors.a.spacing_mm=1.5")["sensors"]["c"]["spacing_mm"] == 0.5
    with pytest.raises(PipelineError, match=r"^param 'sensors\.c\.spacing_mm' = 0\.0 \(-p sensors\.c\.spacing_mm=0\)"):
        _load(ranged, None, "sensors.c.spacing_mm=0")


def test_values_in_range_pass_and_null_passes_only_where_allowed(ranged):
    p = _load(ranged, None, "steps=1000", "spp=9", "size=[16, 512]", "seed_ref=3")
    assert (p["steps"], p["spp"], p["size"], p["seed_ref"]) == (1000, 9, [16, 512], 3)
    (ranged.parent / "ranges.yaml").write_text(RANGES.replace("seed_ref: {ge: 0, whole: true, nullable: true}",
                                                              "seed_ref: {ge: 0}"))
    with pytest.raises(PipelineError, match=r"^param 'seed_ref' = None \(.*params\.yaml:4\) must not be null"):
        _load(ranged)


@pytest.mark.parametrize("text,message", [
    ("steps: {gte: 1}\n", r"ranges file .*ranges\.yaml:1: 'steps' has unknown rule\(s\) gte \(known: "),
    ("stpes: {ge: 1}\n", r"ranges file .*ranges\.yaml:1: 'stpes' names no param"),
    ("sensors.*.spacing: {gt: 0}\n", r"ranges file .*ranges\.yaml:1: 'sensors\.\*\.spacing' names no param"),
    ("steps: {ge: one}\n", r"ranges file .*ranges\.yaml:1: 'steps' ge must be a number, got 'one'"),
    ("steps: 5\n", r"ranges file .*ranges\.yaml:1: the rule of 'steps' must be a mapping such as \{gt: 0\}"),
])
def test_mistakes_in_the_ranges_file_are_one_line(ranged, text, message):
    (ranged.parent / "ranges.yaml").write_text(text)
    with pytest.raises(PipelineError, match=message):
        _load(ranged)


def test_a_yaml_alias_bomb_is_refused_quickly_and_merge_keys_still_work(ranged):
    """Nine levels of ten aliases expand to 10^9 values; the count is linear in the file."""
    import time
    lines = ["a0: &a0 [x, x, x, x, x, x, x, x, x, x]"]
    lines += [f"a{i}: &a{i} [{', '.join([f'*a{i - 1}'] * 10)}]" for i in range(1, 10)]
    ranged.write_text(RANGED + "\n".join(lines) + "\n")
    t0 = time.perf_counter()
    with pytest.raises(PipelineError, match=rf"^params file {ranged}: its aliases expand to more than "
                                            r"200000 values \(an alias bomb\?\)"):
        _load(ranged)
    with pytest.raises(PipelineError, match=r"^override 'steps=.*': its aliases expand to more than 200000"):
        P.parse_override("steps=" + "{" + ", ".join(s.replace(": ", ": ", 1) for s in lines) + "}")
    assert time.perf_counter() - t0 < 5
    ranged.write_text(RANGED)
    assert _load(ranged)["sensors"]["b"] == {"spacing_mm": 0.5, "material": "hard"}
