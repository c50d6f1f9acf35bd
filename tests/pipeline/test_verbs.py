"""The inspection verbs and their --json contracts; metrics baselines; dvc export."""
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from toyproject import cli, run_json, statuses
from tests.helpers import data_offset


def test_ls_show_get(toy):
    out = run_json(toy)
    keys = {n["name"]: n["key"] for n in out["nodes"]}
    rows = json.loads(cli(toy, "ls", "--json").stdout)
    assert {r["name"] for r in rows} == set(keys)
    assert all(set(r) == {"name", "node", "key", "path", "bytes", "created"} for r in rows)
    assert all(Path(r["path"]).stat().st_size == r["bytes"] for r in rows)
    show = json.loads(cli(toy, "show", "frames", "--json").stdout)
    assert show["datasets"] == {"images": {"shape": [40, 4, 4], "dtype": "uint8"},
                                "reference": {"shape": [4, 4], "dtype": "uint8"},
                                "t": {"shape": [40], "dtype": "float64"}}
    assert show["attrs"] == {"n": 16} and show["provenance"]["inputs"] == {"base": keys["base"]}
    by_key = json.loads(cli(toy, "show", keys["frames"][:10], "--json").stdout)
    assert by_key["key"] == keys["frames"]
    assert cli(toy, "get", "shifted[letter=b]").stdout.strip().endswith(f"{keys['shifted[letter=b]']}.h5")
    p = cli(toy, "get", "shifted", check=False)
    assert p.returncode == 2 and "names 2 instances" in p.stderr


def test_dag_formats(toy):
    dag = json.loads(cli(toy, "dag", "--json", "summary").stdout)
    assert [n["name"] for n in dag["nodes"]] == ["base", "scaled", "shifted[letter=a]", "shifted[letter=b]",
                                                 "frames", "summary"]
    assert ["shifted[letter=a]", "summary"] in dag["edges"] and len(dag["edges"]) == 7
    dot = cli(toy, "dag", "--dot").stdout
    assert dot.startswith("digraph pipeline") and '"scaled" -> "shifted[letter=b]";' in dot


def test_metrics_and_baseline(toy, tmp_path):
    run_json(toy)
    m = json.loads(cli(toy, "metrics", "--json").stdout)
    assert m["toy/frames"] == 40.0 and set(m) == {"toy/frames", "toy/total"}
    base = tmp_path / "baseline.yaml"
    cli(toy, "metrics", "--save-baseline", str(base))
    doc = yaml.safe_load(base.read_text())
    assert doc["metrics"] == m
    assert cli(toy, "metrics", "--baseline", str(base)).returncode == 0
    # a baseline 10 better than now: a regression unless the tolerance allows 10
    doc["metrics"]["toy/total"] = m["toy/total"] - 10
    doc["tolerances"] = {"toy/*": {"abs": 1.0}}
    base.write_text(yaml.safe_dump(doc))
    p = cli(toy, "metrics", "--baseline", str(base), check=False)
    assert p.returncode == 1 and "REGRESSION toy/total" in p.stdout and "1 regressions in 2 metrics" in p.stdout
    doc["tolerances"] = {"toy/total": {"rel": 20 / abs(m["toy/total"])}}
    base.write_text(yaml.safe_dump(doc))
    assert cli(toy, "metrics", "--baseline", str(base)).returncode == 0
    # saving again keeps the tolerances and their comments verbatim, and only the metrics change
    base.write_text("# why: noisy\n" + yaml.safe_dump({"tolerances": doc["tolerances"]}) + "metrics: {old: 1.0}\n")
    cli(toy, "metrics", "--save-baseline", str(base))
    assert base.read_text().startswith("# why: noisy\ntolerances:")
    assert yaml.safe_load(base.read_text()) == {"tolerances": doc["tolerances"], "metrics": m}
    # merging keeps the worse value per metric (frames: higher is not better, so the larger)
    base.write_text("# why: noisy\n" + yaml.safe_dump({"tolerances": doc["tolerances"]}) +
                    yaml.safe_dump({"metrics": {"toy/frames": 50.0, "toy/total": m["toy/total"] - 3,
                                                "old/r2_fx": 0.5}}))
    cli(toy, "metrics", "--merge-baseline", str(base))
    assert base.read_text().startswith("# why: noisy\ntolerances:")
    assert yaml.safe_load(base.read_text())["metrics"] == {"old/r2_fx": 0.5, "toy/frames": 50.0,
                                                           "toy/total": m["toy/total"]}
    doc["metrics"]["toy/gone"] = 1.0
    base.write_text(yaml.safe_dump(doc))
    p = cli(toy, "metrics", "--baseline", str(base), check=False)
    assert p.returncode == 1 and "toy/gone" in p.stdout and "missing" in p.stdout


def test_report_from_store(toy):
    run_json(toy)
    out = cli(toy, "report", "--out", "rep").stdout.strip()
    page = Path(toy / "rep" / "index.html").read_text()
    assert out.endswith("rep/index.html") and "toy/total" in page and "shifted[letter=a]" in page


def test_gc_keeps_current(toy):
    run_json(toy)
    run_json(toy, "-p", "seed=4")
    run_json(toy, "-p", "seed=5")
    # seed=5 is the current plan, the refs and the last run; seed=3 and 4 are only in older runs
    assert "12 artifacts to remove" in cli(toy, "gc", "--keep-runs", "1", "--dry-run", "-p", "seed=5").stdout
    assert "6 artifacts removed" in cli(toy, "gc", "--keep-runs", "2", "-p", "seed=5").stdout
    assert "6 artifacts removed" in cli(toy, "gc", "--keep-runs", "1", "-p", "seed=5").stdout
    assert set(statuses(run_json(toy, "-p", "seed=5")).values()) == {"cached"}
    assert statuses(run_json(toy))["base"] == "ran"


def test_gc_keeps_the_current_plan_when_an_upstream_is_damaged(toy):
    """The current params' keys come from the records, not from re-digesting: a damaged
    `base` (which a run recomputes to the same content) still gives the keys of everything
    after it, though the refs now name another run's artifacts."""
    current = {n["name"]: n["key"] for n in run_json(toy)["nodes"]}
    run_json(toy, "-p", "scale=3.0")              # the refs and the last run name these
    objects = toy / "artifacts" / "objects"
    path = objects / f"{current['base']}.h5"
    import h5py
    with h5py.File(path, "r") as f:
        offset = data_offset(f["x"])
    with open(path, "r+b") as fh:              # a flipped bit of its data (and a new mtime)
        fh.seek(offset)
        b = fh.read(1)
        fh.seek(offset)
        fh.write(bytes([b[0] ^ 0x01]))
    out = cli(toy, "gc", "--keep-runs", "0").stdout
    assert "0 artifacts removed" in out, out
    for name, key in current.items():
        assert (objects / f"{key}.h5").exists(), name
    again = statuses(run_json(toy))
    assert again["base"] == "ran" and again["scaled"] == "cutoff" and again["summary"] == "cached"


def test_gc_removes_only_checkpoints_no_planned_key_can_resume(toy):
    """A checkpoint of a key the current plan holds (built or not) stays; those of other keys
    (older params, code since changed), with their .bad and .tmp files, go."""
    run_json(toy)
    plan = json.loads(cli(toy, "status", "--json", "-p", "seed=9").stdout)["nodes"]
    planned = next(n["key"] for n in plan if n["status"] != "cached")
    staging = toy / "artifacts" / "staging"
    staging.mkdir()
    for name in (f"{planned}.ckpt", "0123abcd.ckpt", "0123abcd.ckpt.bad", "0123abcd.ckpt.tmp"):
        (staging / name).write_text("x")
    dry = cli(toy, "gc", "--dry-run", "-p", "seed=9").stdout
    assert "would remove staging/0123abcd.ckpt.bad" in dry and planned not in dry
    assert "0 artifacts to remove, 3 checkpoints" in dry and len(list(staging.iterdir())) == 4
    assert ", 3 checkpoints" in cli(toy, "gc", "-p", "seed=9").stdout
    assert [p.name for p in staging.iterdir()] == [f"{planned}.ckpt"]


def _env_with_bin():
    bin_dir = str(Path(sys.executable).parent)
    repo = str(Path(__file__).resolve().parents[2])
    return {**os.environ, "PATH": bin_dir + os.pathsep + os.environ["PATH"], "PYTHONPATH": repo}


def test_dvc_export_and_repro(toy):
    pytest.importorskip("dvc")
    cli(toy, "dvc")
    doc = yaml.safe_load((toy / "dvc.yaml").read_text())
    stage = doc["stages"]["shifted"]         # a node's instances: one foreach stage
    assert stage["foreach"] == {"a": {"letter": "a"}, "b": {"letter": "b"}}
    assert stage["do"]["cmd"] == "pipeline run 'shifted[letter=${item.letter}]'"
    assert stage["do"]["params"] == ["letters", "offset.${item.letter}"]
    assert stage["do"]["deps"] == ["artifacts/refs/scaled.json", "toy/nodes.py"]
    assert stage["do"]["outs"] == [{"artifacts/refs/shifted@letter=${item.letter}.json": {"cache": False}}]
    assert doc["stages"]["scaled"]["deps"] == ["artifacts/refs/base.json", "toy/helpers.py", "toy/nodes.py"]
    assert cli(toy, "dvc", "--check").returncode == 0
    env = _env_with_bin()
    dvc = [sys.executable, "-m", "dvc"]
    subprocess.run(dvc + ["init", "--no-scm", "-q"], cwd=toy, env=env, check=True)
    r = subprocess.run(dvc + ["repro"], cwd=toy, env=env, capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stdout + r.stderr
    assert set(statuses(run_json(toy)).values()) == {"cached"}
    r = subprocess.run(dvc + ["repro"], cwd=toy, env=env, capture_output=True, text=True, timeout=300)
    assert r.returncode == 0 and "Running stage" not in r.stdout
    (toy / "params.yaml").write_text((toy / "params.yaml").read_text().replace("b: 5.0", "b: 6.0"))
    r = subprocess.run(dvc + ["repro"], cwd=toy, env=env, capture_output=True, text=True, timeout=300)
    assert r.returncode == 0 and "Running stage 'shifted@b'" in r.stdout
    assert "Running stage 'shifted@a'" not in r.stdout
    (toy / "dvc.yaml").write_text("stages: {}\n")
    assert cli(toy, "dvc", "--check", check=False).returncode == 1


def test_merged_baseline_keeps_the_worse_value_in_each_metrics_direction():
    from pipeline.metrics import merged_worse
    base = {"s/a/r2_fx": 0.5, "s/a/mae_fx": 1.0, "s/a/iou": 0.9, "only/base": 2.0}
    cur = {"s/a/r2_fx": 0.7, "s/a/mae_fx": 1.4, "s/a/iou": 0.8, "only/cur": 3.0}
    assert merged_worse(base, cur) == {"only/base": 2.0, "only/cur": 3.0, "s/a/iou": 0.8,
                                       "s/a/mae_fx": 1.4, "s/a/r2_fx": 0.5}


def test_report_metrics_and_status_name_the_profile_the_store_was_built_with(toy):
    """A store built with --profile ci, then looked at with no profile: the verbs say so in one
    line and name the flag; with the flag, or once the default is built, they say nothing."""
    (toy / "params").mkdir(exist_ok=True)
    (toy / "params" / "ci.yaml").write_text("scale: 3.0\n")
    cli(toy, "run", "--profile", "ci")
    note = ("note: the store's last run used the ci profile, this command the default one; "
            "pass --profile ci to see its results")
    for verb in (["metrics"], ["status"], ["report", "--out", str(toy / "report")]):
        p = cli(toy, *verb, check=False)
        assert note in p.stderr.splitlines(), (verb, p.stderr)
        assert "note:" not in cli(toy, *verb, "--profile", "ci").stderr
    cli(toy, "run")
    assert "note:" not in cli(toy, "status").stderr
