"""The studies homo, material and hetero on the authors' released dataset (`data.source:
authors`): the catalogue's sensors and pairs, the graph's wiring (the twin's plan unchanged),
and a homo study run through the CLI on a tiny dataset in their layout (authors_fixture)."""
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from pipeline import Graph, Wiring
from stages import catalogue as C
from stages.common import InputError
from tests.helpers import ROOT, load_params
from tests.stages.capture import authors_fixture as fx

AUTHORS = {"data_source": "authors"}


def _folders(root: Path, sets: dict) -> Path:
    """A dataset's sensor folders only (what the plan-time listings read), and coefficient files."""
    for set_name, sensors in sets.items():
        for s in sensors:
            (root / "training" / fx.IMG[set_name] / s).mkdir(parents=True)
            if set_name in fx.COEFF:
                fx.write_coefficients(root / "training", set_name, s)
    return root


@pytest.fixture()
def folders(tmp_path):
    return _folders(tmp_path / "dataset", {"homo": ["Circle-II", "Array-II", "Array-I"],
                                           "modulus": ["ratio_8", "ratio_18", "ratio_6"],
                                           "hetero": ["tactip", "gelsight"]})


def test_authors_members_pairs_and_groups(folders):
    """Each force study runs on its set's sensors in the authors' order, every ordered pair, the
    study's `sensors` still capping how many; the material groups go by the ratio; sim-m2m and
    everything the twin renders stay on the twin."""
    ci = load_params("ci")
    sensors, studies = ci["sensors"], ci["studies"]          # ci: homo 2, material 2, hetero star
    data = {**AUTHORS, "data_root": str(folders)}
    assert C.members(sensors, studies, "homo", **data) == ["Array-I", "Array-II"]
    assert C.members(sensors, {**studies, "homo": {"sensors": 0}}, "homo", **data) == [
        "Array-I", "Array-II", "Circle-II"]
    assert C.pairs(sensors, studies, "hetero", **data) == [["gelsight", "tactip"], ["tactip", "gelsight"]]
    all3 = {**studies, "material": {"pairs": "star", "sensors": 3}}
    assert C.groups(sensors, all3, "material", **data) == {
        "hard_to_soft": [["ratio_6", "ratio_8"], ["ratio_6", "ratio_18"], ["ratio_8", "ratio_18"]],
        "soft_to_hard": [["ratio_8", "ratio_6"], ["ratio_18", "ratio_6"], ["ratio_18", "ratio_8"]]}
    patterns = C.members(sensors, studies, "sim-m2m")
    assert C.members(sensors, studies, "sim-m2m", **data) == patterns == ["Array1", "Array2", "Array3", "Array4"]
    assert C.force_sensors(sensors, studies, **data) == [
        "Array-I", "Array-II", "ratio_6", "ratio_8", "gelsight", "tactip"]
    assert C.active(sensors, studies, **data) == patterns + C.force_sensors(sensors, studies, **data)
    assert C.active(sensors, studies, **data, twin_only=True) == patterns
    assert C.by_source(sensors, studies, "render", **data) == patterns
    assert C.bodies(sensors, studies, **data) == ["sim"] and C.bodies(sensors, studies, True, **data) == []
    assert len(C.transfer_pairs(sensors, studies, **data)) == 2 + 2 + 2
    # M2M pairs frames within a set only: a contact number of one set is no location of another's
    assert C.m2m_members(sensors, studies, **data) == {"homo": ["Array-I", "Array-II"], "modulus": ["ratio_6", "ratio_8"],
                                                      "hetero": ["gelsight", "tactip"]}
    assert C.m2m_of(sensors, studies, **data)["ratio_8"] == "m2m[fit=modulus]"
    assert C.m2m_members(sensors, studies) == {"twin": C.force_sensors(sensors, studies)}
    seq = C.sequences(sensors, studies, **data)
    assert seq["Array1"] == "markers[skin=Array1]" and seq["ratio_6"] == "ingest[sensor=ratio_6]"
    assert C.sequence_node(sensors, studies, **data) == {"node": "ingest", "var": "sensor"}
    cal = C.calibrations(sensors, studies, **data)
    assert cal == {"Array-I": "", "Array-II": "", "ratio_6": "authors_calibration[sensor=ratio_6]",
                   "ratio_8": "authors_calibration[sensor=ratio_8]",
                   "gelsight": "authors_calibration[sensor=gelsight]", "tactip": "authors_calibration[sensor=tactip]"}
    # the twin: its markers and its bodies' calibrate
    assert C.sequence_node(sensors, studies) == {"node": "markers", "var": "skin"}
    assert C.calibrations(sensors, studies)["gelsight-A-I"] == "calibrate[sensor=gelsight-A-II]"
    assert set(C.sequences(sensors, studies).values()) == {f"markers[skin={s}]" for s in C.active(sensors, studies)}


def test_a_study_whose_set_is_missing_names_it(folders, tmp_path):
    ci = load_params("ci")
    partial = _folders(tmp_path / "partial", {"homo": ["Array-I"], "hetero": ["tactip", "uskin"]})
    data = {**AUTHORS, "data_root": str(partial)}
    args = (ci["sensors"], ci["studies"])
    assert C.members(*args, "material", **data) == [] and C.pairs(*args, "homo", **data) == []
    with pytest.raises(InputError, match=rf"^data.root: the modulus set needs at least two sensors for a "
                                         rf"transfer study, found none under {partial}/training$"):
        C.members(*args, "material", **data, check=True)
    with pytest.raises(InputError, match=r"^data.root: the homo set needs at least two sensors .* found Array-I "):
        C.members(*args, "homo", **data, check=True)
    assert C.members(*args, "hetero", **data, check=True) == ["uskin", "tactip"]          # their order
    with pytest.raises(C.CatalogueError, match=r"^sensor 'uskin' is both a twin sensor of params `sensors` and "):
        C.active({**ci["sensors"], "uskin": {**ci["sensors"]["uskin"], "studies": ["sim-m2m"]}},
                 {**ci["studies"], "sim-m2m": {"sensors": 0}}, **data)
    with pytest.raises(C.CatalogueError, match=r"^this node runs on the twin's sensors"):
        C.twin_data("authors")
    with pytest.raises(C.CatalogueError, match=r"^data.source must be one of twin, authors, got 'real'$"):
        C.members(*args, "homo", data_source="real")


def test_the_graph_reads_ingest_and_the_authors_curves(folders):
    """With the authors' data every study's node reads `ingest` (and `authors_calibration`
    where the set has curves); the twin renders only sim-m2m's patterns; control, a twin of a
    gripper, has nothing to run on and is left out of the default targets."""
    from stages.graph import GRAPH
    params = load_params("ci")
    params["data"].update(source="authors", root=str(folders))
    inst = GRAPH.expand(params)
    assert [n for n in inst if n.startswith("markers[")] == [f"markers[skin=Array{k}]" for k in range(1, 5)]
    assert not any(n.startswith(("calibrate[", "deform[sensor=gelsight")) for n in inst)
    t = inst["transfer[source=ratio_8,target=ratio_6,seed=0]"]
    assert t.inputs == {"translated": "translate[source=ratio_8,target=ratio_6]",
                        "source_calibration": "authors_calibration[sensor=ratio_8]",
                        "target_calibration": "authors_calibration[sensor=ratio_6]",
                        "target_markers": "ingest[sensor=ratio_6]", "captured_calibrations": {}}
    assert "source_calibration" not in inst["transfer[source=Array-I,target=Array-II,seed=0]"].inputs
    # one M2M fine-tune per set, each gathering its own sensors
    assert inst["m2m[fit=hetero]"].inputs["markers"] == {"gelsight": "ingest[sensor=gelsight]",
                                                         "tactip": "ingest[sensor=tactip]"}
    assert inst["translate[source=ratio_8,target=ratio_6]"].inputs["model"] == "m2m[fit=modulus]"
    assert inst["m2m_sim"].inputs["markers"] == {f"Array{k}": f"markers[skin=Array{k}]" for k in range(1, 5)}
    assert inst["features[skin=Array1]"].inputs["markers"] == "markers[skin=Array1]"
    assert inst["features[skin=gelsight]"].inputs["markers"] == "ingest[sensor=gelsight]"
    assert inst["homo"].inputs["markers"] == {s: f"ingest[sensor={s}]" for s in ("Array-I", "Array-II")}
    assert inst["control"].problem.startswith("this node runs on the twin's sensors")
    default = GRAPH.select(inst, None)
    assert "control" not in default and "summary" in default


# -- the twin's plan is the one it was --------------------------------------------------------

# the references the twin's nodes had before the authors' data could take their place
TWIN_INPUTS = {
    "own": {"markers": "markers[skin={skin}]"}, "features": {"markers": "markers[skin={skin}]"},
    "flow_warp": {"source_markers": "markers[skin={source}]", "target_markers": "markers[skin={target}]"},
    "m2m": {"markers": "markers[skin=@skins]"}, "ablation": {"markers": "markers[*]"},
    "translate": {"model": "m2m", "source_markers": "markers[skin={source}]", "target_markers": "markers[skin={target}]"},
    "curves": {"markers": "markers[*]"},
    "transfer": {"source_calibration": "calibrate[sensor={source_spec[body]}]",
                 "target_calibration": "calibrate[sensor={target_spec[body]}]",
                 "source_punch": "calibrate_punch[sensor={source_spec[body]}]",
                 "target_punch": "calibrate_punch[sensor={target_spec[body]}]",
                 "target_markers": "markers[skin={target}]"},
    **{s: {"markers": "markers[skin=@members]"} for s in ("homo", "material", "hetero")},
    "control": {"model": "transfer[source={model_pair[0]},target={model_pair[1]},seed=0]",
                "supervised": "own[skin={model_pair[1]},seed=0]"},
}
SPECS = {"source_spec": "sensors.{source}", "target_spec": "sensors.{target}"}


@pytest.mark.parametrize("profile", [None, "ci", "paper", "allpairs"])
def test_the_twins_plan_is_unchanged(profile):
    """With data.source twin every instance keeps its name, params and inputs (so the stores'
    cache keys), against the graph with the twin's plain references and no Wiring; transfer
    alone no longer reads its sensors' whole catalogue entries (it took only their body), and
    the one M2M fine-tune of the twin no longer takes its sensors as a param (it fine-tunes on
    every sensor it gathers)."""
    from stages.graph import GRAPH, _cat
    plain = Graph()
    for name, node in GRAPH.nodes.items():
        params = {k: v for k, v in node.params.items() if not isinstance(v, Wiring)}
        plain.node(name, node.func, inputs={**node.inputs, **TWIN_INPUTS.get(name, {})},
                   params={**params, **(SPECS if name == "transfer" else {}),
                           **({"skins": _cat("force_sensors")} if name == "m2m" else {})}, grid=node.grid,
                   source=node.source, on_demand=node.on_demand)
    params = load_params(profile)
    now, before = GRAPH.expand(params), plain.expand(params)
    assert list(now) == list(before)
    for n, inst in now.items():
        old = before[n]
        if inst.node.name == "transfer":
            assert {k: v for k, v in old.params.items() if k not in SPECS} == inst.params, n
        elif inst.node.name == "m2m":
            assert {k: v for k, v in old.params.items() if k != "skins"} == inst.params, n
            assert old.params["skins"] == list(inst.inputs["markers"]), n
        else:
            assert old.params == inst.params, n
        assert old.inputs == inst.inputs, n


# -- a homo study on a tiny dataset in the authors' layout, through the CLI --------------------

HOMO = ("Array-I", "Array-II")
INDENTERS = ("sphere", "prism", "cylinder", "moon", "wave")   # the ci profile's: train, validation moon, test wave


def _cli(*args):
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    env.pop("PIPELINE_STORE", None)
    return subprocess.run([sys.executable, "-m", "pipeline", *args], cwd=ROOT, env=env, capture_output=True,
                          text=True, timeout=900)


@pytest.fixture(scope="module")
def homo_run(tmp_path_factory):
    base = tmp_path_factory.mktemp("authors")
    root = base / "dataset"
    fx.write_dataset(root, sets={"homo": {HOMO[0]: {}, HOMO[1]: {"jpg": True}},
                                 "hetero": {"gelsight": {}, "tactip": {}}},
                     indenters={"homo": INDENTERS, "hetero": INDENTERS}, points=(1,))
    (root / "training" / "hetero" / "img" / "tactip" / "moon" / "1" / "0001.npy").unlink()   # one set broken
    data = ["--profile", "ci", "-p", "data.source=authors", "-p", f"data.root={root}", "--store", str(base / "store")]
    p = _cli("run", "homo", *data, "--json")
    assert p.returncode == 0, p.stderr[-3000:]
    return root, base / "store", data, json.loads(p.stdout)


def test_a_homo_study_runs_on_the_authors_sensors(homo_run):
    from pipeline.artifact import Artifact
    from stages.common import attrs_of
    root, store, data, out = homo_run
    ran = [n["name"] for n in out["nodes"]]
    assert [n for n in ran if n.startswith("ingest[")] == [f"ingest[sensor={s}]" for s in HOMO]
    assert not any(n.startswith(("calibrate[", "authors_calibration[")) for n in ran)
    metrics = json.loads(_cli("metrics", "--json", *data).stdout)
    pairs = [f"{a}_{b}" for a in HOMO for b in HOMO if a != b]
    for split in ("homo", "homo_val"):
        assert sorted({k.split("/")[1] for k in metrics if k.startswith(f"{split}/")} - {"mean"}) == sorted(pairs)
        for pair in pairs:
            for m in ("source_only", "genforce", "genforce_comp", "genforce_plus", "oracle"):
                assert np.isfinite(metrics[f"{split}/{pair}/{m}/mae_total"]), (split, pair, m)
            # one gel, no calibration: the compensation is the identity
            assert metrics[f"{split}/{pair}/genforce_comp/mae_total"] == metrics[f"{split}/{pair}/genforce/mae_total"]
        assert np.isfinite(metrics[f"homo/{pairs[0]}/m2m/fid"])
    with Artifact(_cli("get", "m2m[fit=homo]", *data).stdout.strip()) as art:
        attrs = attrs_of(art)
    assert attrs["skins"] == list(HOMO) and attrs["base_skins"] == ["Array1", "Array2", "Array3", "Array4"]
    with Artifact(_cli("get", f"transfer[source={HOMO[0]},target={HOMO[1]},seed=0]", *data).stdout.strip()) as art:
        attrs = attrs_of(art)
    assert attrs["compensation_identity"] is True and attrs["curves"] is None


def test_one_sets_bad_file_stops_only_the_studies_that_read_it(homo_run):
    """The hetero set lacks a frame: homo ran beside it (homo_run, its own M2M fine-tune),
    and hetero stops with one line naming the file, exit 2, nothing of the store lost (what
    it finished before, gelsight's data, stays)."""
    root, store, data, out = homo_run
    ran = [n["name"] for n in out["nodes"]]
    assert "m2m[fit=homo]" in ran and not any("hetero" in n or "tactip" in n for n in ran)
    before = sorted(os.listdir(store / "objects"))
    p = _cli("run", "hetero", *data)
    assert p.returncode == 2 and p.stderr.count("\n") == 1, p.stderr[-3000:]
    missing = root / "training" / "hetero" / "img" / "tactip" / "moon" / "1" / "0001.npy"
    assert p.stderr == f"pipeline: error: node ingest[sensor=tactip]: missing frame {missing}\n"
    assert set(before) <= set(os.listdir(store / "objects"))


def test_a_study_without_its_set_is_one_line_and_runs_nothing(homo_run):
    root, store, data, _ = homo_run
    before = sorted(os.listdir(store / "objects"))
    p = _cli("run", "material", *data)
    assert p.returncode == 2
    assert p.stderr == (f"pipeline: error: node material: data.root: the modulus set needs at least two sensors "
                        f"for a transfer study, found none under {root}/training\n")
    assert sorted(os.listdir(store / "objects")) == before


def test_a_material_study_of_one_marker_layout_runs(tmp_path):
    """Before: two modulus gels of one layout (identical reference images, as ratio_6 and
    ratio_18 are here) stopped M2M's fine-tune, and with it every study.  Now they are one
    style: the fine-tune trains nothing for them, their translation is the identity, and the
    material study reports every method."""
    from pipeline.artifact import Artifact
    from stages.common import attrs_of
    root = tmp_path / "dataset"
    truth = fx.write_dataset(root, sets={"modulus": {"ratio_6": {}, "ratio_18": {}}},
                             indenters={"modulus": INDENTERS}, points=(1,))
    assert np.array_equal(fx.mask("ratio_6", "", 0, -1), fx.mask("ratio_18", "", 0, -1)) and len(truth) == 2
    data = ["--profile", "ci", "-p", "data.source=authors", "-p", f"data.root={root}", "--store", str(tmp_path / "store")]
    p = _cli("run", "material", *data)
    assert p.returncode == 0, p.stderr[-3000:]
    with Artifact(_cli("get", "m2m[fit=modulus]", *data).stdout.strip()) as art:
        assert attrs_of(art)["same_style"] == {"ratio_18": "ratio_6"} and attrs_of(art)["steps"] == 0
    with Artifact(_cli("get", "translate[source=ratio_6,target=ratio_18]", *data).stdout.strip()) as art:
        assert attrs_of(art)["same_style"] is True
    metrics = json.loads(_cli("metrics", "--json", *data).stdout)
    for m in ("source_only", "genforce", "genforce_comp", "genforce_plus", "oracle"):
        for row in ("ratio_6_ratio_18", "ratio_18_ratio_6", "mean", "hard_to_soft", "soft_to_hard"):
            assert np.isfinite(metrics[f"material/{row}/{m}/mae_total"]), (row, m)
        assert metrics[f"material/mean/{m}/mae_total_sd"] >= 0
