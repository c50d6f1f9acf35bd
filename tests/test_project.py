"""The project's own graph, params and generated files stay consistent."""
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from pipeline import params as P
from pipeline.config import find_project
from pipeline.errors import PipelineError

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


def test_the_readme_is_a_manual_that_opens_with_the_two_commands():
    import re
    text = (ROOT / "README.md").read_text()
    assert len(text.splitlines()) <= 400
    block = text.split("```bash\n", 1)[1].split("```", 1)[0].splitlines()
    assert [line.split()[:2] for line in block] == [["make", "run"], ["make", "test"]]
    for path in ["README.md", "params.yaml", *map(str, (ROOT / "params").glob("*.yaml"))]:
        dated = re.findall(r"\b20\d\d-\d\d-\d\d\b", (ROOT / path).read_text())
        assert not dated, f"{path} keeps a diary: {dated[:3]}"
    for image in re.findall(r"!\[[^]]*\]\(([^)]+)\)", text):
        assert (ROOT / image).is_file(), image


def test_every_installed_package_is_pinned_by_the_constraints():
    """Before: pyproject's loose ranges let a fresh machine install newer packages than the
    baseline was made with, and the ci metrics moved.  setup.sh installs under
    constraints.txt, which pins every dependency, and this venv holds exactly those versions."""
    import re
    import tomllib
    from importlib.metadata import distributions

    def norm(name):
        return re.sub(r"[-_.]+", "-", name).lower()
    setup = (ROOT / "scripts" / "setup.sh").read_text()
    assert setup.count("-c constraints.txt") == 3
    pins = {}
    for line in (ROOT / "constraints.txt").read_text().splitlines():
        if line and not line.startswith("#"):
            name, _, version = line.partition("==")
            pins[norm(name)] = version
    deps = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    wanted = deps["dependencies"] + deps["optional-dependencies"]["dev"]
    names = {norm(re.split(r"[<>=\[ ]", d, 1)[0]) for d in wanted}
    assert names - {"torch"} <= set(pins), sorted(names - {"torch"} - set(pins))
    installed = {norm(d.metadata["Name"]): d.version for d in distributions()}
    assert {n: (v, installed.get(n)) for n, v in pins.items() if installed.get(n) != v} == {}


@pytest.mark.parametrize("profile", ["default", "ci", "paper", "allpairs", "seeds"])
def test_profiles_load(profile):
    project = find_project(ROOT)
    assert project.ranges_file == ROOT / "params.ranges.yaml"
    params = P.load(project.params_file, profile, [], project.profiles_dir, project.ranges_file)
    project.load_graph().expand(params)  # every reference resolves, every value is in its range


# values each of which only a node refused, with exit 1 and its traceback, some minutes in
@pytest.mark.parametrize("override,rule", [
    ("collection_trajectory.n_points=-3", ">= 1"),
    ("m2m.pretrain.steps=-5", ">= 1"),
    ("m2m.finetune.batch_size=0", ">= 1"),
    ("m2m.pretrain.lr=-1.0", ">= 0"),
    ("m2m.pretrain.steps=1000000000000000000000000", "<= 10000000"),
    ("force.steps=-1", ">= 1"),
    ("render.spp=-4", "one of 1, 4, 9, 16, 25, 36, 49, 64"),
    ("render.spp=2", "one of 1, 4, 9, 16, 25, 36, 49, 64"),
    ("sensors.sim.spacing_mm=0.0", "> 0"),
    ("sensors.gelsight-r8.spacing_mm=0", "> 0"),          # its value came through `<<: *gelsight`
    ("calibration_trajectory.n_steps=0", ">= 1"),
    ("patterns.image_size=[1000000, 1000000]", "<= 4096"),
    ("capture.sensor=gelsight-Z-IX", "name an entry of sensors"),
    ("data.source=lab", "one of twin, authors"),
    ("segmentation.method=watershed", "one of otsu, grabcut"),
    ("control.objects.grape.shape=cube", "one of sphere, cylinder, flat"),
    ("studies.homo.pairs=ring2", "one of ring, star, all"),
    ("force.config.input_size=40", "a multiple of 16"),
    ("materials.r6.nu=0.5", "< 0.5"),
])
def test_a_value_out_of_its_range_is_refused_before_anything_runs(override, rule):
    project = find_project(ROOT)
    key = override.split("=")[0]
    with pytest.raises(PipelineError) as err:
        P.load(project.params_file, "ci", [override], project.profiles_dir, project.ranges_file)
    message = str(err.value)
    assert message.startswith(f"param '{key}") and f"(-p {override}) must " in message
    assert f"{rule} (range '" in message
    assert message.endswith(")") and "params.ranges.yaml:" in message


def test_the_cli_refuses_an_out_of_range_value_in_one_line_and_builds_nothing(tmp_path):
    store = tmp_path / "store"
    p = pipeline("run", "collection_trajectory", "--profile", "ci", "--store", str(store),
                 "-p", "collection_trajectory.n_points=-3", check=False)
    assert p.returncode == 2 and p.stdout == "" and "Traceback" not in p.stderr
    assert p.stderr == ("pipeline: error: param 'collection_trajectory.n_points' = -3 "
                        "(-p collection_trajectory.n_points=-3) must be >= 1 (range "
                        f"'collection_trajectory.n_points' in {ROOT / 'params.ranges.yaml'}:16)\n")
    assert not store.exists()


@pytest.mark.parametrize("key,digits,message", [
    ("m2m.pretrain.steps", 400, "must be <= 10000000 (range 'm2m.*.steps'"),
    ("force.lr", 400, "must be a finite number, got an integer of 400 digits"),
    ("force.lr", 5000, "value out of range in override 'force.lr=999"),
])
def test_a_huge_number_in_a_param_is_one_line(key, digits, message):
    """Before: an int or float param given 400 nines died in an OverflowError traceback."""
    p = pipeline("status", "--profile", "ci", "-p", f"{key}={'9' * digits}", check=False)
    assert p.returncode == 2 and p.stderr.count("\n") == 1 and "Traceback" not in p.stderr
    assert message in p.stderr and len(p.stderr) < 400, p.stderr


def _ranges() -> dict:
    from pipeline.params import safe_load
    return safe_load((ROOT / "params.ranges.yaml").read_text())


def _constant(package: str, name: str):
    """A constant of the first module of `package` that defines it (modules may move)."""
    import importlib
    import pkgutil
    pkg = importlib.import_module(package)
    for info in pkgutil.iter_modules(pkg.__path__):
        module = importlib.import_module(f"{package}.{info.name}")
        if name in vars(module):
            return vars(module)[name]
    raise AssertionError(f"no {name} in {package}")


def test_the_ranges_option_lists_are_the_nodes_own():
    """An option a node adds or drops must be added to or dropped from params.ranges.yaml too."""
    r = _ranges()
    one_of = lambda key: r[key].get("one_of") or r[key]["items"]["one_of"]   # noqa: E731
    from stages.capture.devices import DEVICES
    from stages.catalogue import PAIRINGS, STUDIES
    from stages.control.objects import SHAPES, TARGET_N
    from stages.force.model import INPUT_MODES
    from stages.force.plus import ADDITIONS
    from stages.markers import mitsuba_backend, segment, unify, uskin
    from stages.markers.patterns import PATTERNS
    from stages.sim.indenters import ALL_INDENTERS
    expected = {
        "indenters.names": ALL_INDENTERS, "calibration_trajectory.indenter": ALL_INDENTERS,
        "plus.punch_indenter": ALL_INDENTERS,
        "patterns.names": PATTERNS, "sensors.*.look": unify.LOOKS, "sensors.*.variant": uskin.VARIANTS,
        "render.backend": ("auto", *mitsuba_backend.VARIANTS), "segmentation.method": segment.METHODS,
        "segmentation.*.polarity": segment.POLARITIES, "capture.devices": tuple(DEVICES),
        "control.objects.*.shape": SHAPES, "control.objects.*.fragility": tuple(TARGET_N),
        "force.config.input_mode": INPUT_MODES, "studies.*.pairs": PAIRINGS,
        "plus.additions": ADDITIONS,
    }
    assert r["sensors.*.studies"]["items"]["key_of"] == "studies"
    assert set(STUDIES) == set(P.load(ROOT / "params.yaml")["studies"])
    for key, options in expected.items():
        assert sorted(one_of(key)) == sorted(options), key


def test_allpairs_adds_pairs_and_changes_nothing_else():
    """The allpairs profile runs every ordered pair of the 12 simulation patterns and of the
    default profile's sensors; every node instance the default has keeps its params there (so a
    default store serves it), except the studies, the ablation and the learning curve, whose
    pair lists grow."""
    from itertools import permutations
    project = find_project(ROOT)
    graph = project.load_graph()
    base = graph.expand(P.load(project.params_file, None, [], project.profiles_dir))
    every = graph.expand(P.load(project.params_file, "allpairs", [], project.profiles_dir))
    studies = {"sim_m2m", "homo", "material", "hetero", "ablation", "curves"}
    changed = sorted(n for n, inst in base.items()
                     if n.partition("[")[0] not in studies and (n not in every or every[n].params != inst.params))
    assert changed == []
    pairs = lambda inst: {tuple(p) for g in inst.params["groups"].values() for p in g}
    twins = {"homo": ["gelsight-A-I", "gelsight-A-II", "gelsight-C-I", "gelsight-C-II", "gelsight-D-I"],
             "material": ["gelsight-r6", "gelsight-r10", "gelsight-r18"],
             "hetero": ["gelsight-A-II", "tactip", "uskin-3axis"]}
    for study, skins in twins.items():
        assert pairs(every[study]) == set(permutations(skins, 2)), study
        assert pairs(base[study]) <= pairs(every[study]), study
    assert len({n.rsplit(",seed=", 1)[0] for n in every if n.startswith("transfer[")}) == 20 + 6 + 6
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
    assert f"render[skin={new}]" in added and f"markers[skin={new}]" in added
    seeds = P.load(project.params_file, None, [], project.profiles_dir)["force"]["seeds"]
    assert {f"own[skin={new},seed={k}]" for k in seeds} <= set(added) and seeds
    assert inst[f"render[skin={new}]"].inputs["deform"] == "deform[sensor=gelsight-A-II]"
    assert not any(n.startswith(("deform[", "calibrate[")) for n in added)
    assert new in inst["m2m[fit=twin]"].inputs["markers"]
    homo = {tuple(p) for g in inst["homo"].params["groups"].values() for p in g}
    assert {("gelsight-A-II", new), (new, "gelsight-A-II")} <= homo
    assert f"transfer[source={new},target=gelsight-A-II,seed=0]" in added


def test_the_ablation_runs_only_when_named():
    """`pipeline run` with no target leaves out the ablation; named, it gathers every transfer
    pair's models of every regressor seed (3 or more), which the studies read too."""
    project = find_project(ROOT)
    params = P.load(project.params_file, "seeds", [], project.profiles_dir)
    graph = project.load_graph()
    inst = graph.expand(params)
    default = set(graph.closure(inst, graph.select(inst, None)))
    assert "ablation" not in default
    named = set(graph.closure(inst, graph.select(inst, ["ablation"])))
    transfers = sorted(n for n in named if n.startswith("transfer["))
    assert transfers == sorted(n for n in inst if n.startswith("transfer[")) and set(transfers) <= default
    assert len(params["force"]["seeds"]) >= 3
    assert len(transfers) == len({n.rsplit(",seed=", 1)[0] for n in transfers}) * len(params["force"]["seeds"])


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
    """Force regressors that never learn (learning rate 0): the studies' errors regress past
    k seed spreads and the comparison exits 1, while metrics upstream of the force models
    (segmentation, image metrics: the same bits) stay where they were."""
    store, _ = ci_store
    worse = ("-p", "force.lr=0.0")
    pipeline("run", "homo", "material", "hetero", "--profile", "ci", "--store", store, *worse)
    p = pipeline("metrics", "--profile", "ci", "--store", store, *worse, "--baseline",
                 str(ROOT / "baselines" / "ci.yaml"), check=False)
    assert p.returncode == 1
    rows = {line.split()[1]: line for line in p.stdout.splitlines() if line.startswith(("ok", "REGRESSION"))}
    failed = {name for name, line in rows.items() if line.startswith("REGRESSION")}
    studies = {name for name in rows if name.split("/")[0].removesuffix("_val") in ("homo", "material", "hetero")}
    # the ci profile's models train 20 steps, so a mean over pairs moves by about its seed
    # spread; the per-pair metrics of every force study regress by the hundred
    assert len(failed & studies) >= len(studies) // 10, len(failed & studies)
    for study in ("homo", "material", "hetero"):
        assert any(name.startswith(f"{study}_val/") for name in failed), study
    assert not any("missing" in rows[name] for name in failed & studies)
    # besides them only the control study's, which this run leaves unbuilt
    assert all(rows[name].split()[-3] == "missing" for name in failed - studies), failed - studies
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


# one instance of each node family whose ci instance takes seconds, not minutes; the rest (the
# studies, control, the transfers' training and the source nodes) are checked by a whole ci run
# in each executor, too slow for the suite
SAME_IN_EVERY_EXECUTOR = [
    "indenters", "sim_trajectory", "collection_trajectory", "calibration_trajectory", "patterns",
    "contact_check", "deform[sensor=sim]", "calibrate[sensor=gelsight-r6]", "punch_trajectory",
    "calibrate_punch[sensor=gelsight-r6]", "render[skin=Array1]",
    "taxels[skin=uskin-3axis]", "markers[skin=Array1]", "features[skin=Array1]",
    "flow_warp[source=Array1,target=Array2]", "m2m_sim", "m2m[fit=twin]",
    "translate_sim[source=Array1,target=Array2]", "translate[source=gelsight-A-I,target=gelsight-A-II]",
    "own[skin=gelsight-A-II,seed=0]"]
LEFT_TO_A_WHOLE_RUN = {"transfer", "ablation", "curves", "sim_m2m", "homo", "material", "hetero",
                       "control", "summary", "capture", "capture_calibration", "ingest", "authors_calibration"}


def test_every_node_family_is_compared_across_executors_or_listed_as_left_out():
    graph = find_project(ROOT).load_graph()
    compared = {name.partition("[")[0] for name in SAME_IN_EVERY_EXECUTOR}
    assert compared | LEFT_TO_A_WHOLE_RUN == set(graph.nodes) and not compared & LEFT_TO_A_WHOLE_RUN


def test_node_families_make_the_same_content_inline_as_in_a_process_pool(ci_store, tmp_path):
    """`make run` built the ci store in a pool of spawned processes (each with its share of the
    cores); recomputed here by the inline executor from the same inputs, each instance has the
    same content digest.  flow_warp's did not: its features took torch's default threads."""
    import shutil
    store, _ = ci_store
    copy = tmp_path / "store"
    shutil.copytree(store, copy)
    built = {n["name"]: n["key"] for n in json.loads(pipeline("status", "--profile", "ci", "--json", "--store",
                                                                  str(copy), *SAME_IN_EVERY_EXECUTOR).stdout)["nodes"]}
    before = {name: json.loads((copy / "index" / f"{key}.json").read_text())["digest"] for name, key in built.items()}
    out = json.loads(pipeline("run", "--profile", "ci", "--store", str(copy), "--force", "--json",
                              *SAME_IN_EVERY_EXECUTOR).stdout)
    ran = {n["name"]: n for n in out["nodes"] if n["status"] == "ran"}
    assert sorted(ran) == sorted(SAME_IN_EVERY_EXECUTOR)
    after = {name: json.loads((copy / "index" / f"{n['key']}.json").read_text())["digest"] for name, n in ran.items()}
    assert {n: d for n, d in after.items() if d != before[n]} == {}


# the twin's nodes: bit for bit the same on any x86-64 machine (README, "Reproducibility")
TWIN = ("indenters", "sim_trajectory", "collection_trajectory", "calibration_trajectory", "patterns",
        "deform", "render", "taxels", "markers", "calibrate", "contact_check")


def test_the_twin_has_the_same_digests_with_the_cpu_features_restricted(ci_store, tmp_path):
    """Before: another machine rendered other marker images (segment IoU, every `before` FID
    differed), as numpy, OpenCV and Dr.Jit chose their kernels by the CPU.  Built again here
    with torch's and oneDNN's AVX2 kernels and OpenCV's without AVX2/AVX-512 (another
    machine's choices), every twin node has the native run's content digest."""
    sys.path.insert(0, str(ROOT / "scripts"))
    from ci_baseline import RESTRICTED
    store, _ = ci_store
    other = tmp_path / "restricted"
    env = {**os.environ, "PYTHONPATH": str(ROOT), **RESTRICTED}
    env.pop("PIPELINE_STORE", None)
    p = subprocess.run([sys.executable, "-m", "pipeline", "run", *TWIN, "--profile", "ci", "--json",
                        "--executor", "process", "--store", str(other)],
                       cwd=ROOT, env=env, capture_output=True, text=True, timeout=600)
    assert p.returncode == 0, p.stderr[-3000:]
    built = json.loads(p.stdout)["nodes"]
    assert {n["name"].partition("[")[0] for n in built} == set(TWIN) and len(built) > 20

    def digest(root, key):
        return json.loads((Path(root) / "index" / f"{key}.json").read_text())["digest"]
    assert {n["name"]: digest(other, n["key"]) for n in built if digest(other, n["key"]) != digest(store, n["key"])} == {}


def test_a_damaged_input_stops_its_dependent_and_is_recomputed_first(ci_store, tmp_path):
    """Before: a byte flipped in deform[sensor=uskin]'s displacement (size and mtime kept) was
    read without error by a forced taxels, which kept the wrong content under its key.  Each
    chunk's Fletcher32 checksum now fails the read: taxels stops with one line naming deform's
    artifact, the next run recomputes deform, and every artifact equals the undamaged run's."""
    import shutil
    import h5py
    from tests.helpers import data_offset
    store, _ = ci_store
    copy = tmp_path / "store"
    shutil.copytree(store, copy)
    nodes = json.loads(pipeline("status", "--profile", "ci", "--json", "--store", str(copy)).stdout)["nodes"]
    keys = {n["name"]: n["key"] for n in nodes}
    digests = {name: json.loads((copy / "index" / f"{key}.json").read_text())["digest"] for name, key in keys.items()}
    deform = copy / "objects" / f"{keys['deform[sensor=uskin]']}.h5"
    with h5py.File(deform, "r") as f:
        ds = f["displacement"]
        offset = ds.id.get_chunk_info(ds.id.get_num_chunks() // 2).byte_offset + 100 if ds.chunks else data_offset(ds)
    st = deform.stat()
    with open(deform, "r+b") as fh:
        fh.seek(offset)
        b = fh.read(1)
        fh.seek(offset)
        fh.write(bytes([b[0] ^ 0x10]))
    os.utime(deform, ns=(st.st_atime_ns, st.st_mtime_ns))
    p = pipeline("run", "taxels[skin=uskin-3axis]", "--force", "--profile", "ci", "--store", str(copy), check=False)
    assert p.returncode == 2 and p.stderr.count("\n") == 1 and "Traceback" not in p.stderr
    assert (f"input 'deform' of taxels[skin=uskin-3axis]: artifact {keys['deform[sensor=uskin]']} is corrupt"
            in p.stderr), p.stderr
    again = {n["name"]: n["status"] for n in json.loads(pipeline(
        "run", "--profile", "ci", "--json", "--store", str(copy)).stdout)["nodes"]}
    assert again["deform[sensor=uskin]"] == "ran" and again["taxels[skin=uskin-3axis]"] in ("cached", "cutoff")
    assert pipeline("verify", "--store", str(copy)).returncode == 0
    after = {name: json.loads((copy / "index" / f"{key}.json").read_text())["digest"] for name, key in keys.items()}
    assert {n: d for n, d in after.items() if d != digests[n]} == {}


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
    target = "transfer[source=gelsight-A-II,target=tactip,seed=0]"

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
    # genforce_plus's shear_calibration reads the calibrations' shear legs: the emulated rig
    # drives the captured leg at the sensor's stroke, so its F/T reads the twin's shear
    assert twin["plus"]["shear_calibration"]["calibrated"] is True
    assert 0 < twin["plus"]["shear_calibration"]["scale"] < 1                 # TacTip feels less shear
    assert captured["plus"]["shear_calibration"]["scale"] == pytest.approx(
        twin["plus"]["shear_calibration"]["scale"], rel=1e-2)
    assert captured["shear_ratios"]["target"] == pytest.approx(twin["shear_ratios"]["target"], rel=1e-2)
    # punch_calibration reads the twin's punch curves beside the twin's prism curves, never
    # beside a captured calibration: into TacTip a flat face presses less than the prism says
    assert twin["plus"]["punch_calibration"]["calibrated"] is True
    assert 0 < twin["plus"]["punch_calibration"]["scale"] < 0.8
    assert captured["plus"]["punch_calibration"] == {"scale": 1.0, "calibrated": False}
    assert captured["punch_scale"] is None
