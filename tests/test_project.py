"""The project's own graph, params and generated files stay consistent."""
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from pipeline import params as P
from pipeline.config import find_project

ROOT = Path(__file__).resolve().parents[1]


def pipeline(*args, check=True):
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    env.pop("PIPELINE_STORE", None)
    p = subprocess.run([sys.executable, "-m", "pipeline", *args], cwd=ROOT, env=env,
                       capture_output=True, text=True, timeout=600)
    if check and p.returncode:
        raise AssertionError(p.stdout + p.stderr)
    return p


def test_dvc_yaml_in_sync():
    p = pipeline("dvc", "--check", check=False)
    assert p.returncode == 0, "dvc.yaml is out of date: run `pipeline dvc` and commit it"
    assert (ROOT / "dvc.yaml").stat().st_size <= 60_000        # a node per stage: readable


@pytest.mark.parametrize("profile", ["default", "ci", "paper", "allpairs"])
def test_profiles_load(profile):
    project = find_project(ROOT)
    params = P.load(project.params_file, profile, [], project.profiles_dir)
    project.load_graph().expand(params)  # every reference resolves


def test_allpairs_adds_pairs_and_changes_nothing_else():
    """The allpairs profile runs every ordered pair of the 12 simulation patterns and of the
    default profile's sensors; every node instance the default has keeps its params there (so a
    default store serves it), except the studies and the ablation, whose pair lists grow."""
    from itertools import permutations
    project = find_project(ROOT)
    graph = project.load_graph()
    base = graph.expand(P.load(project.params_file, None, [], project.profiles_dir))
    every = graph.expand(P.load(project.params_file, "allpairs", [], project.profiles_dir))
    studies = {"sim_m2m", "homo", "material", "hetero", "ablation"}
    changed = sorted(n for n, inst in base.items()
                     if n not in studies and (n not in every or every[n].params != inst.params))
    assert changed == []
    pairs = lambda inst: {tuple(p) for g in inst.params["groups"].values() for p in g}
    twins = {"homo": ["gelsight-A-I", "gelsight-A-II", "gelsight-C-I", "gelsight-C-II", "gelsight-D-I"],
             "material": ["gelsight-r6", "gelsight-r10", "gelsight-r18"],
             "hetero": ["gelsight-A-II", "tactip", "uskin-3axis"]}
    for study, skins in twins.items():
        assert pairs(every[study]) == set(permutations(skins, 2)), study
        assert pairs(base[study]) <= pairs(every[study]), study
    assert len([n for n in every if n.startswith("transfer[")]) == 20 + 6 + 6
    patterns = every["m2m_sim"].params["skins"]
    assert {tuple(p) for p in every["sim_m2m"].params["pairs"]} == set(permutations(patterns, 2))
    assert len([n for n in every if n.startswith("translate_sim[")]) == 132


def test_a_sensor_copied_under_a_new_name_joins_its_family(tmp_path):
    """Copying the GelSight A-II entry of params.yaml under a new name, and nothing else, puts
    the new sensor into rendering, markers, its own regressor, M2M's fine-tune and the homo
    study's pairs, on A-II's body (no second deformation)."""
    import shutil
    text = (ROOT / "params.yaml").read_text()
    start = text.index("  gelsight-A-II: {")
    end = text.index("\n  gelsight-A-I: {")
    entry = text[start:end].replace("gelsight-A-II:", "gelsight-B-I:", 1)
    (tmp_path / "params.yaml").write_text(text[:end] + "\n" + entry + text[end:])
    shutil.copytree(ROOT / "params", tmp_path / "params")
    project = find_project(ROOT)
    graph = project.load_graph()
    base = graph.expand(P.load(project.params_file, None, [], project.profiles_dir))
    inst = graph.expand(P.load(tmp_path / "params.yaml", None, [], tmp_path / "params"))
    added = sorted(set(inst) - set(base))
    new = "gelsight-B-I"
    assert f"render[skin={new}]" in added and f"markers[skin={new}]" in added and f"own[skin={new}]" in added
    assert inst[f"render[skin={new}]"].inputs["deform"] == "deform[sensor=gelsight-r10]"
    assert not any(n.startswith(("deform[", "calibrate[")) for n in added)
    assert new in inst["m2m"].params["skins"]
    homo = {tuple(p) for g in inst["homo"].params["groups"].values() for p in g}
    assert {("gelsight-A-II", new), (new, "gelsight-A-II")} <= homo
    assert f"transfer[source={new},target=gelsight-A-II]" in added


def test_the_ablation_runs_only_when_named():
    """`pipeline run` with no target leaves out the ablation and the seeds it alone needs; named,
    it gathers every transfer pair's seeds."""
    project = find_project(ROOT)
    params = P.load(project.params_file, None, [], project.profiles_dir)
    graph = project.load_graph()
    inst = graph.expand(params)
    default = set(graph.closure(inst, graph.select(inst, None)))
    assert not any(n == "ablation" or n.startswith("transfer_seed[") for n in default)
    named = set(graph.closure(inst, graph.select(inst, ["ablation"])))
    seeds = [n for n in named if n.startswith("transfer_seed[")]
    pairs = [n for n in inst if n.startswith("transfer[")]
    assert len(seeds) == len(pairs) * len(params["ablation"]["seeds"]) and 0 not in params["ablation"]["seeds"]


@pytest.fixture(scope="module")
def ci_store(tmp_path_factory):
    """The whole DAG on the ci profile, once for this module, through the README's first
    command (`make run`, here with ARGS naming the profile and a scratch store)."""
    store = str(tmp_path_factory.mktemp("ci") / "store")
    env = {k: v for k, v in os.environ.items() if k not in ("PIPELINE_STORE", "MAKEFLAGS", "MAKELEVEL")}
    p = subprocess.run(["make", "-s", "run", f"ARGS=--profile ci --json --store {store}"], cwd=ROOT,
                       env=env, capture_output=True, text=True, timeout=900)
    if p.returncode:
        raise AssertionError(p.stdout[-3000:] + p.stderr[-3000:])
    return store, json.loads(p.stdout.strip().splitlines()[-1])   # after any set-up output


def test_ci_profile_runs_and_is_then_cached(ci_store):
    store, first = ci_store
    assert {n["status"] for n in first["nodes"]} == {"ran"}
    names = {n["name"] for n in first["nodes"]}
    for study in ("sim_m2m", "homo", "material", "hetero", "control", "contact_check"):
        assert study in names                                # every study is a default target
    assert "capture" not in names                            # source nodes run only when named
    assert not any(n.startswith(("ingest", "authors_calibration")) for n in names)   # data.source twin
    again = json.loads(pipeline("run", "--profile", "ci", "--json", "--store", store).stdout)
    assert {n["status"] for n in again["nodes"]} == {"cached"}
    assert pipeline("verify", "--store", store).returncode == 0


def test_ci_metrics_match_the_baseline(ci_store):
    """CI's regression gate: every ci metric within its tolerance of baselines/ci.yaml."""
    store, _ = ci_store
    p = pipeline("metrics", "--profile", "ci", "--store", store, "--baseline",
                 str(ROOT / "baselines" / "ci.yaml"), check=False)
    assert p.returncode == 0, p.stdout[-3000:] + p.stderr[-2000:]
    assert p.stdout.splitlines()[-1].startswith("0 regressions in ")


def test_a_worse_model_fails_the_baseline(ci_store):
    """Force regressors that never learn (learning rate 0): the studies' normal-force errors
    regress past their tolerances and the comparison exits 1, while metrics upstream of the
    force models (segmentation, image metrics) stay within theirs."""
    store, _ = ci_store
    worse = ("-p", "force.lr=0.0")
    pipeline("run", "homo", "material", "hetero", "--profile", "ci", "--store", store, *worse)
    p = pipeline("metrics", "--profile", "ci", "--store", store, *worse, "--baseline",
                 str(ROOT / "baselines" / "ci.yaml"), check=False)
    assert p.returncode == 1
    rows = {line.split()[1]: line for line in p.stdout.splitlines() if line.startswith(("ok", "REGRESSION"))}
    for name in ("hetero/mean/oracle/mae_fz", "homo/mean/oracle/mae_fz", "material/mean/oracle/r2_fz"):
        assert rows[name].startswith("REGRESSION") and "missing" not in rows[name], rows[name]
    assert rows["segment/tactip/iou"].startswith("ok") and rows["hetero/mean/m2m/fid"].startswith("ok")


def test_report_of_the_ci_store(ci_store, tmp_path):
    """The report is built from the store alone: a section per study, figures on disk."""
    store, _ = ci_store
    out = tmp_path / "report"
    p = pipeline("report", "--profile", "ci", "--store", store, "--out", str(out))
    page = (out / "index.html").read_text()
    assert p.stdout.strip() == str(out / "index.html")
    for study in ("sim-m2m", "homo", "material", "hetero", "control", "segment"):
        assert f"id='ns-{study}'" in page or f'id="ns-{study}"' in page, study
    figures = list((out / "figures").glob("*.png"))
    assert len(figures) >= 20 and all(f.stat().st_size > 1000 for f in figures[:5])


def test_noop_run_imports_no_science(ci_store):
    """Deciding that nothing is stale must not import torch, mitsuba, cv2 or even h5py."""
    store, _ = ci_store
    code = ("import sys; from pipeline.cli import main; "
            f"rc = main(['run', '--profile', 'ci', '--store', {store!r}]); "
            "heavy = sorted(m for m in ('torch', 'mitsuba', 'cv2', 'h5py', 'trimesh', 'scipy', 'numpy') "
            "if m in sys.modules); print('HEAVY', heavy); sys.exit(rc)")
    p = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True,
                       env={**os.environ, "PYTHONPATH": str(ROOT)})
    assert p.returncode == 0, p.stderr
    assert "HEAVY []" in p.stdout


def test_transfers_compensate_with_a_captured_calibration(ci_store):
    """A sensor listed in capture.calibration.sensors: its transfers wait for its captured
    calibration, named in one line; captured (emulated rig), they compensate with it, and the
    emulated capture's curves are the twin's."""
    from pipeline.artifact import Artifact
    from stages.common import attrs_of
    store, _ = ci_store
    target = "transfer[source=gelsight-A-II,target=tactip]"

    def attrs(*args):
        path = pipeline("get", target, "--profile", "ci", "--store", store, *args).stdout.strip()
        return attrs_of(Artifact(path))
    twin = attrs()
    listed = ("--profile", "ci", "--store", store, "-p", "capture.calibration.sensors=[tactip]")
    p = pipeline("run", target, *listed, check=False)
    assert p.returncode == 2                                      # the CLI's exit status for a refusal
    assert ("source node capture_calibration[sensor=tactip] has no artifact for these params; capture "
            "it explicitly with `pipeline run 'capture_calibration[sensor=tactip]'`") in p.stdout + p.stderr
    pipeline("run", "capture_calibration", *listed)
    pipeline("run", target, *listed)
    captured = attrs(*listed[4:])
    assert captured["calibration"] == {"target": "capture_calibration[sensor=tactip]"}
    assert "calibration" not in twin
    for end in ("source", "target"):
        for curve in ("loading", "unloading"):
            assert captured["curves"][end][curve] == pytest.approx(twin["curves"][end][curve], rel=1e-3, abs=1e-3)
    # genforce_plus's gains read the same frames with the same labels, so they agree too
    for gain in ("shear_gain", "fz_gain"):
        assert captured["plus"][gain]["gain"] == pytest.approx(twin["plus"][gain]["gain"], rel=0.05, abs=0.02)
