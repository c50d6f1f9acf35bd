"""Crashes, concurrency, corruption and bad input never damage the store."""
import json
import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import h5py
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from pipeline.cli import main
import toyproject
from toyproject import cli, run_json, statuses
from tests.helpers import data_offset

REPO = Path(__file__).resolve().parents[2]


def _env():
    return {**os.environ, "PYTHONPATH": str(REPO)}


def test_sigkill_mid_write_leaves_no_partial_artifact(toy):
    run_json(toy, "base")  # so that the plan knows the key of frames
    plan = json.loads(cli(toy, "run", "--dry-run", "--json", "frames", "-p", "slow=0.4").stdout)
    key = {n["name"]: n["key"] for n in plan["nodes"]}["frames"]
    objects = toy / "artifacts" / "objects"
    proc = subprocess.Popen([sys.executable, "-m", "pipeline", "run", "frames", "-p", "slow=0.4"],
                            cwd=toy, env=_env(), stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    assert key is not None
    deadline = time.time() + 60
    while not list(objects.glob(f".tmp-{key}-*")) and time.time() < deadline:
        time.sleep(0.05)
    time.sleep(0.5)  # some chunks are written
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    assert proc.returncode == -signal.SIGKILL
    assert list(objects.glob(f".tmp-{key}-*")), "the writer was killed before it started"
    assert not (objects / f"{key}.h5").exists()
    out = json.loads(cli(toy, "status", "--json", "frames", "-p", "slow=0.4").stdout)
    assert {n["name"]: n["status"] for n in out["nodes"]}["frames"] == "stale"
    out = run_json(toy, "frames", "-p", "slow=0.01")
    assert statuses(out)["frames"] == "ran"
    with h5py.File(objects / f"{out['nodes'][-1]['key']}.h5") as f:
        assert f["images"].shape == (40, 4, 4)
    cli(toy, "gc")
    assert not list(objects.glob(".tmp-*"))


def _running(pid: int) -> bool:
    """The process exists and is not a zombie (an orphan's zombie may wait for a reaper)."""
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] != "Z"
    except (FileNotFoundError, IndexError):
        return False


def _start_slow_frames(toy, *args: str) -> tuple[subprocess.Popen, int]:
    """`pipeline run frames --executor process ARGS` with a 5 s frames node, and the pid of the
    worker computing it, once it has started."""
    f = toy / "toy" / "nodes.py"
    f.write_text(f.read_text().replace(
        "def frames(base, slow):\n",
        "def frames(base, slow):\n    open('frames.pid', 'w').write(str(os.getpid()))\n"))
    run_json(toy, "base")
    proc = subprocess.Popen([sys.executable, "-m", "pipeline", "run", "frames", "--executor", "process",
                             *args, "-p", "slow=5"], cwd=toy, env=_env(), stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)
    pid_file = toy / "frames.pid"
    deadline = time.time() + 60
    while not (pid_file.exists() and pid_file.read_text()) and time.time() < deadline:
        time.sleep(0.05)
    return proc, int(pid_file.read_text())


def test_sigterm_stops_a_process_run_and_its_workers(toy):
    """SIGTERM to `pipeline run --executor process` (a job scheduler's time limit) ends it as
    Ctrl-C does, one line and exit 130, and stops the worker computing a node instead of
    leaving it orphaned; the next run computes that node."""
    proc, worker = _start_slow_frames(toy)
    assert worker != proc.pid and _running(worker)
    proc.send_signal(signal.SIGTERM)
    _, err = proc.communicate(timeout=30)
    assert proc.returncode == 130 and err.strip().splitlines()[-1] == "pipeline: interrupted"
    deadline = time.time() + 10
    while _running(worker) and time.time() < deadline:
        time.sleep(0.05)
    assert not _running(worker), "the worker computes on after its run was stopped"
    assert statuses(run_json(toy, "frames", "-p", "slow=0.01"))["frames"] == "ran"


def _children(pid: int) -> list[int]:
    out = []
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except (OSError, IndexError):
            continue
        if int(fields[1]) == pid:
            out.append(int(stat.parent.name))
    return out


def test_workers_and_their_resource_tracker_exit_when_the_run_is_killed(toy):
    """SIGKILL leaves no handler to stop the workers: each must notice its parent's death itself,
    or it computes on, orphaned, with multiprocessing's resource tracker."""
    proc, worker = _start_slow_frames(toy, "--jobs", "2")
    helpers = _children(proc.pid)
    assert worker in helpers and len(helpers) >= 2, helpers      # the worker and the resource tracker
    proc.kill()
    proc.wait()
    deadline = time.time() + 5
    while any(_running(p) for p in helpers) and time.time() < deadline:
        time.sleep(0.05)
    assert not [p for p in helpers if _running(p)], "processes outlive the killed run"


def test_concurrent_runs_compute_each_node_once(toy, tmp_path):
    log = tmp_path / "log.txt"
    env = {**_env(), "TOY_LOG": str(log)}
    args = [sys.executable, "-m", "pipeline", "run", "--json", "-p", "slow=0.2"]
    procs = [subprocess.Popen(args, cwd=toy, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
             for _ in range(2)]
    outs = [p.communicate(timeout=120) for p in procs]
    assert [p.returncode for p in procs] == [0, 0], outs
    lines = log.read_text().split()
    assert sorted(lines) == sorted(set(lines)) and len(lines) == 6
    a, b = (statuses(json.loads(o)) for o, _ in outs)
    assert all(sorted([a[n], b[n]]) in (["cached", "ran"], ["cutoff", "ran"]) for n in a)


def _flip(path: Path, dataset: str) -> None:
    with h5py.File(path, "r") as f:
        offset = data_offset(f[dataset])
    with open(path, "r+b") as fh:
        fh.seek(offset)
        b = fh.read(1)
        fh.seek(offset)
        fh.write(bytes([b[0] ^ 0x01]))


@pytest.mark.parametrize("damage", ["flip", "flip-keep-mtime", "truncate"])
def test_corrupt_artifact_reported_by_verify_and_recomputed(toy, damage):
    first = run_json(toy)
    key = {n["name"]: n["key"] for n in first["nodes"]}["base"]
    path = toy / "artifacts" / "objects" / f"{key}.h5"
    st = path.stat()
    if damage == "truncate":
        with open(path, "r+b") as fh:
            fh.truncate(st.st_size - 100)
    else:
        _flip(path, "x")
        if damage == "flip-keep-mtime":
            os.utime(path, ns=(st.st_atime_ns, st.st_mtime_ns))
    v = cli(toy, "verify", check=False)
    assert v.returncode == 1 and f"corrupt {key}" in v.stdout and "1 corrupt" in v.stdout
    out = run_json(toy)
    assert statuses(out)["base"] == "ran"
    assert statuses(out)["scaled"] == "cutoff"  # same content as before the damage
    assert {n["name"]: n["key"] for n in out["nodes"]} == {n["name"]: n["key"] for n in first["nodes"]}
    assert cli(toy, "verify").returncode == 0
    assert len(list((toy / "artifacts" / "corrupt").glob(f"{key}-*.h5"))) == 1


def _digests(store: Path) -> dict:
    recs = [json.loads(p.read_text()) for p in (store / "index").glob("*.json")]
    return {r["instance"]: (r["key"], r["digest"]) for r in recs}


def _thread_env(_task):
    return {v: os.environ.get(v) for v in ("OMP_NUM_THREADS", "MKL_NUM_THREADS")}


def test_process_workers_share_the_cores(monkeypatch):
    """Each of N spawned workers gets cores // N OpenMP threads, unless the user set a value."""
    from pipeline.executors import ProcessExecutor
    monkeypatch.setattr(os, "cpu_count", lambda: 8)   # the parent computes the share
    monkeypatch.delenv("OMP_NUM_THREADS", raising=False)
    monkeypatch.setenv("MKL_NUM_THREADS", "3")
    ex = ProcessExecutor(4)
    try:
        assert ex.result(ex.submit(_thread_env, {})) == {"OMP_NUM_THREADS": "2", "MKL_NUM_THREADS": "3"}
    finally:
        ex.close()


@pytest.mark.parametrize("executor", ["inline", "process"])
def test_every_node_runs_inside_the_projects_node_context(toy, executor):
    """[tool.pipeline] node_context names a context manager the worker enters around every
    node, whichever executor runs it (the project pins its numeric libraries' threads so)."""
    (toy / "pyproject.toml").write_text(toyproject.PYPROJECT + 'node_context = "toy.ctx:pinned"\n')
    (toy / "toy" / "ctx.py").write_text(
        "import contextlib, os\n\n\n@contextlib.contextmanager\ndef pinned():\n"
        "    os.environ['TOY_CTX'] = '3'\n    try:\n        yield\n    finally:\n"
        "        del os.environ['TOY_CTX']\n")
    f = toy / "toy" / "nodes.py"
    f.write_text(f.read_text().replace(
        '    return {"x": normalise(np.asarray(base["x"])) * scale}',
        '    return {"x": normalise(np.asarray(base["x"])) * scale, "ctx": np.array(float(os.environ.get("TOY_CTX", -1)))}'))
    run_json(toy, "scaled", "--executor", executor, "--jobs", "2")
    with h5py.File(cli(toy, "get", "scaled").stdout.strip()) as art:
        assert art["ctx"][()] == 3.0


@pytest.mark.parametrize("executor", ["process", "dask"])
def test_parallel_executors_match_serial(toy, executor):
    run_json(toy, "--store", "serial")
    out = run_json(toy, "--store", "par", "--executor", executor, "--jobs", "2", timeout=300)
    assert set(statuses(out).values()) == {"ran"}
    assert _digests(toy / "par") == _digests(toy / "serial")
    assert len(_digests(toy / "serial")) == 6


def test_dask_scheduler_address(toy):
    distributed = pytest.importorskip("distributed")
    with distributed.LocalCluster(n_workers=1, threads_per_worker=1, processes=True,
                                  dashboard_address=None) as cluster:
        out = run_json(toy, "--executor", "dask", "--address", cluster.scheduler_address, timeout=300)
    assert set(statuses(out).values()) == {"ran"}
    p = cli(toy, "run", "--executor", "dask", "--address", "tcp://127.0.0.1:1", check=False, timeout=120)
    assert p.returncode == 2 and p.stderr.count("\n") == 1 and "cannot reach Dask scheduler" in p.stderr


def test_node_failure_is_reported_with_traceback(toy):
    f = toy / "toy" / "nodes.py"
    f.write_text(f.read_text().replace('    _log("scaled")', '    _log("scaled")\n    raise ValueError("bad scale")'))
    p = cli(toy, "run", check=False)
    assert p.returncode == 1
    assert "Traceback" in p.stderr and p.stderr.strip().splitlines()[-1] == \
        "pipeline: error: node scaled failed: ValueError: bad scale"
    assert json.loads(cli(toy, "status", "--json", "base").stdout)["nodes"][0]["status"] == "cached"


def test_device_error_is_one_line_and_staging_dir_is_given(toy):
    """A node may take `staging_dir` (<store>/staging); an exception class with
    user_error = True (a device gone) is a one-line error, exit 2, like bad input."""
    f = toy / "toy" / "nodes.py"
    f.write_text(f.read_text().replace(
        "def scale(base, scale):\n",
        "class DeviceError(RuntimeError):\n    user_error = True\n\n\n"
        "def scale(base, scale, staging_dir):\n"
        "    open(os.path.join(staging_dir, 'partial.txt'), 'w').write('kept')\n"
        "    raise DeviceError('netft 127.0.0.1:1: no reply for 2.0 s')\n"))
    p = cli(toy, "run", check=False)
    assert p.returncode == 2 and "Traceback" not in p.stderr
    assert p.stderr.strip() == "pipeline: error: node scaled: netft 127.0.0.1:1: no reply for 2.0 s"
    assert (toy / "artifacts" / "staging" / "partial.txt").read_text() == "kept"


def test_checkpoint_is_a_path_per_key_kept_on_failure_and_deleted_on_commit(toy):
    """A node may take `checkpoint`: <store>/staging/<its cache key>.ckpt.  A run that fails
    leaves what the node saved there; the next run of the same key finds it (here it resumes
    from the saved value) and, once the artifact is committed, the file is gone."""
    f = toy / "toy" / "nodes.py"
    f.write_text(f.read_text().replace(
        "def scale(base, scale):\n",
        "def scale(base, scale, checkpoint):\n"
        "    if not os.path.exists(checkpoint):\n"
        "        open(checkpoint, 'w').write('7')\n"
        "        raise RuntimeError('machine lost')\n"
        "    base = {'x': np.asarray(base['x']) + float(open(checkpoint).read())}\n"))
    p = cli(toy, "run", check=False)
    assert p.returncode != 0 and "machine lost" in p.stderr
    saved = sorted((toy / "artifacts" / "staging").glob("*.ckpt"))
    assert len(saved) == 1 and saved[0].read_text() == "7"
    run_json(toy)
    key, = [n["key"] for n in json.loads(cli(toy, "status", "--json", "scaled").stdout)["nodes"]
            if n["name"] == "scaled"]
    assert saved[0].name == f"{key}.ckpt" and not saved[0].exists()
    assert list((toy / "artifacts" / "staging").iterdir()) == []


# -- bad input: one line, exit 2, never a traceback ------------------------------------

@pytest.mark.parametrize("args,message", [
    (["run", "nope"], "unknown target 'nope'"),
    (["run", "shifted[letter=c]"], "no instance of 'shifted' has those values"),
    (["run", "-p", "seed=x"], "param 'seed' (-p seed=x) must be int, got str 'x'"),
    (["run", "-p", "sead=1"], "unknown param 'sead' (-p sead=1); did you mean 'seed'?"),
    (["run", "--profile", "huge"], "unknown profile 'huge' (known: default, small)"),
    (["run", "--jobs", "many"], "argument --jobs: invalid int value: 'many'"),
    (["show", "ffffff"], "no artifact with key 'ffffff'"),
    (["get", "base"], "base is not built (missing); run `pipeline run 'base'`"),
    (["frobnicate"], "argument verb: invalid choice: 'frobnicate'"),
    (["run", "--executor", "dask", "--address", "foo"], "cannot reach Dask scheduler at foo"),
    (["report", "--out", "/proc/nope"], "cannot write report to /proc/nope"),
    (["run", "shifted[]"], "malformed target or reference 'shifted[]': empty brackets; use shifted or "
                           "shifted[*] for every instance"),
    (["run", "--profile", ""], "--profile is empty: name a profile (default, or a file of params/)"),
    (["run", "--store", ""], "--store is empty: name a store directory (default: artifacts/)"),
    (["verify", "--store", " "], "--store is empty"),
])
def test_bad_input_one_line_exit_2(toy, args, message):
    p = cli(toy, *args, check=False)
    assert p.returncode == 2, p.stderr
    assert p.stderr.count("\n") == 1 and "Traceback" not in p.stderr
    assert message in p.stderr


@pytest.mark.parametrize("text,message", [
    ("metrics: {toy/total: x}\n", "metric 'toy/total' must be a number, got 'x'"),
    ("metrics: {toy/total: 1}\ntolerances: {'toy/*': {abs: x}}\n", "tolerance 'toy/*' abs='x'"),
    ("[1, 2]\n", "must have a 'metrics' mapping"),
])
def test_bad_baseline_one_line(toy, tmp_path, text, message):
    run_json(toy)
    f = tmp_path / "b.yaml"
    f.write_text(text)
    p = cli(toy, "metrics", "--baseline", str(f), check=False)
    assert p.returncode == 2 and p.stderr.count("\n") == 1 and message in p.stderr


def test_malformed_params_file_names_line(toy):
    (toy / "params" / "small.yaml").write_text("size: 8\nseed: [1\n")
    p = cli(toy, "status", "--profile", "small", check=False)
    assert p.returncode == 2 and "malformed YAML in" in p.stderr and "small.yaml:3" in p.stderr


_keys = st.sampled_from(["seed", "scale", "size", "letters", "offset.a", "offset", "slow", "sede",
                         "offset.c", "", "a.b.c", "seed.x"])
_values = st.one_of(st.text(max_size=12), st.integers().map(str), st.floats(allow_nan=True).map(str),
                    st.sampled_from(["[1, 2]", "[a, b]", "{a: 1}", "true", "null", "[", "{", ":", "'"]))


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(key=_keys, value=_values, sep=st.sampled_from(["=", "", " = ", "=="]))
def test_fuzz_params_clean_errors(toy, monkeypatch, capsys, key, value, sep):
    monkeypatch.chdir(toy)
    rc = main(["status", "-p", f"{key}{sep}{value}"])
    err = capsys.readouterr().err
    assert rc in (0, 2)
    if rc == 2:
        assert err.startswith("pipeline: error: ") and err.count("\n") == 1
    else:
        assert err == ""


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(target=st.one_of(st.text(max_size=20), st.sampled_from(
    ["shifted[letter=a]", "shifted[*]", "shifted[", "base]", "[x=1]", "shifted[letter=a,letter=b]",
     "shifted[letter=a]]", "summary[x=1]", "sha\x00", "shifted[letter=a, letter=a]"])))
def test_fuzz_targets_clean_errors(toy, monkeypatch, capsys, target):
    monkeypatch.chdir(toy)
    rc = main(["status", "--", target])
    err = capsys.readouterr().err
    assert rc in (0, 2)
    if rc == 2:
        assert err.startswith("pipeline: error: ") and err.count("\n") == 1


# -- a damaged or missing store: one line naming the culprit, nothing removed -------------

@pytest.mark.parametrize("verb", ["ls", "verify", "metrics", "gc", "report", "show base"])
def test_missing_store_is_named_not_read_as_empty(toy, verb):
    p = cli(toy, *verb.split(), "--store", "no/such/store", check=False)
    assert p.returncode == 2 and p.stderr.count("\n") == 1, p.stderr
    assert "no store at no/such/store: nothing is built there yet (`pipeline run` builds it)" in p.stderr
    assert not (toy / "no").exists()


def test_store_that_is_a_file_is_named(toy):
    (toy / "store.txt").write_text("not a store\n")
    for verb in ("run", "status", "ls"):
        p = cli(toy, verb, "--store", "store.txt", check=False)
        assert p.returncode == 2 and p.stderr.strip() == "pipeline: error: store store.txt is not a directory"


def test_os_error_in_the_store_is_one_line(toy, monkeypatch, capsys):
    """A read-only or full store fails the run with the file and the reason, no traceback."""
    import errno
    from pipeline.store import Store

    def refuse(self, key):
        raise OSError(errno.EROFS, "Read-only file system", str(self.locks / f"{key}.lock"))
    monkeypatch.chdir(toy)
    monkeypatch.setattr(Store, "lock", refuse)
    assert main(["run", "base"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "Traceback" not in err
    assert err.startswith("pipeline: error: cannot use ") and err.rstrip().endswith(".lock: Read-only file system")
    assert str(toy / "artifacts" / "locks") in err


def _flip_superblock_keep_mtime(path: Path) -> None:
    st = path.stat()
    with open(path, "r+b") as fh:   # bytes 16-17: the superblock's version and size fields
        fh.seek(16)
        b = fh.read(2)
        fh.seek(16)
        fh.write(bytes([b[0] ^ 0xFF, b[1] ^ 0xFF]))
    os.utime(path, ns=(st.st_atime_ns, st.st_mtime_ns))


def test_damaged_input_with_its_record_intact_is_moved_aside_not_blamed_on_the_node(toy):
    """Size and mtime still match the index record, so only reading it finds the damage: the
    node that reads it fails with one line naming the input, the file goes to corrupt/, and
    the next run recomputes it (same content, so everything downstream is a cutoff)."""
    first = run_json(toy)
    key = {n["name"]: n["key"] for n in first["nodes"]}["base"]
    path = toy / "artifacts" / "objects" / f"{key}.h5"
    _flip_superblock_keep_mtime(path)
    p = cli(toy, "run", "--force", "scaled", check=False)
    assert p.returncode == 2 and p.stderr.count("\n") == 1 and "Traceback" not in p.stderr
    assert f"node scaled: input 'base' of scaled: artifact {key} is corrupt (unreadable" in p.stderr
    assert "moved to corrupt/" in p.stderr and not path.exists()
    assert len(list((toy / "artifacts" / "corrupt").glob(f"{key}-*.h5"))) == 1
    out = run_json(toy)
    assert statuses(out)["base"] == "ran" and statuses(out)["scaled"] == "cutoff"
    assert cli(toy, "verify").returncode == 0


def test_show_of_a_damaged_artifact_with_its_record_intact(toy):
    first = run_json(toy)
    key = {n["name"]: n["key"] for n in first["nodes"]}["base"]
    _flip_superblock_keep_mtime(toy / "artifacts" / "objects" / f"{key}.h5")
    p = cli(toy, "show", "base", check=False)
    assert p.returncode == 2 and p.stderr.count("\n") == 1 and "Traceback" not in p.stderr
    assert f"base: artifact {key} is corrupt (unreadable" in p.stderr
    assert statuses(run_json(toy))["base"] == "ran"


@pytest.mark.parametrize("damage", ['{"key": 5}', "[1, 2]", '{"digest": "x"}', "null"])
def test_index_records_of_the_wrong_shape_are_rebuilt(toy, damage):
    first = run_json(toy)
    for p in (toy / "artifacts" / "index").glob("*.json"):
        p.write_text(damage)
    assert set(statuses(run_json(toy)).values()) == {"cached"}
    assert len(json.loads(cli(toy, "ls", "--json").stdout)) == len(first["nodes"])
    assert cli(toy, "verify").returncode == 0


def test_refs_of_the_wrong_shape_read_as_missing(toy):
    run_json(toy)
    for p in (toy / "artifacts" / "refs").glob("*.json"):
        p.write_text("[1, 2]")
    out = json.loads(cli(toy, "status", "--json").stdout)
    assert {n["status"] for n in out["nodes"]} == {"cached"}   # the index, not the refs, decides
    assert set(statuses(run_json(toy)).values()) == {"cached"}


@pytest.mark.parametrize("folder,text", [("runs", '{"keys": 5}'), ("runs", "[1]"), ("refs", '["k"]')])
def test_gc_refuses_when_what_a_file_keeps_is_unknown(toy, folder, text):
    run_json(toy)
    run_json(toy, "-p", "seed=4")
    before = sorted(p.name for p in (toy / "artifacts" / "objects").iterdir())
    victim = sorted((toy / "artifacts" / folder).glob("*.json"))[-1]
    victim.write_text(text)
    p = cli(toy, "gc", "-p", "seed=4", check=False)
    assert p.returncode == 2 and p.stderr.count("\n") == 1
    assert f"gc: {victim} is damaged" in p.stderr and "nothing was removed" in p.stderr
    assert sorted(p.name for p in (toy / "artifacts" / "objects").iterdir()) == before


@pytest.mark.parametrize("args,message", [
    (["gc", "--keep-runs", "-1"], "argument --keep-runs: expected a whole number >= 0, got -1"),
    (["run", "-p", "scale=.nan"], "param 'scale' (-p scale=.nan) must be a finite number, got nan"),
    (["run", "-p", "scale=-.inf"], "param 'scale' (-p scale=-.inf) must be a finite number, got -inf"),
    (["run", "-p", "letters=[a, z]"],
     "node 'shifted' has no param 'offset.z' for letter=z: is that value in letters a typo?"),
])
def test_more_bad_input_one_line_exit_2(toy, args, message):
    p = cli(toy, *args, check=False)
    assert p.returncode == 2 and p.stderr.count("\n") == 1 and "Traceback" not in p.stderr
    assert message in p.stderr, p.stderr


def test_recursive_yaml_anchor_and_non_utf8_baseline(toy, tmp_path):
    (toy / "params" / "small.yaml").write_text("offset: &a {a: *a}\n")
    p = cli(toy, "status", "--profile", "small", check=False)
    assert p.returncode == 2 and p.stderr.count("\n") == 1
    assert "small.yaml: a YAML alias contains itself (recursive anchor)" in p.stderr
    run_json(toy)
    bad = tmp_path / "b.yaml"
    bad.write_bytes(b"metrics: {toy/total: 1}\n# \xff\xfe\n")
    p = cli(toy, "metrics", "--baseline", str(bad), check=False)
    assert p.returncode == 2 and p.stderr.strip() == f"pipeline: error: baseline {bad} is not UTF-8 text (byte 26)"


def test_corrupt_folder_that_is_a_file_is_named(toy):
    first = run_json(toy)
    key = {n["name"]: n["key"] for n in first["nodes"]}["base"]
    path = toy / "artifacts" / "objects" / f"{key}.h5"
    with open(path, "r+b") as fh:
        fh.truncate(path.stat().st_size - 100)
    (toy / "artifacts" / "corrupt").write_text("in the way\n")
    p = cli(toy, "status", check=False)
    assert p.returncode == 2 and p.stderr.count("\n") == 1
    assert f"artifact {key} is damaged (" in p.stderr and "cannot be moved aside" in p.stderr
    assert path.exists()


# -- trust: files that are intact but not what their names say ------------------------------

def test_an_artifact_copied_over_another_is_found_by_verify_and_run(toy):
    """A swapped file is intact (its digest matches its content), so only the key it carries
    tells: verify names it, and a run recomputes it instead of feeding it downstream."""
    import shutil
    first = run_json(toy)
    keys = {n["name"]: n["key"] for n in first["nodes"]}
    objects = toy / "artifacts" / "objects"
    total = json.loads(cli(toy, "metrics", "--json").stdout)["toy/total"]
    shutil.copyfile(objects / f"{keys['shifted[letter=b]']}.h5", objects / f"{keys['shifted[letter=a]']}.h5")
    v = cli(toy, "verify", check=False)
    assert v.returncode == 1 and "1 corrupt" in v.stdout
    assert f"corrupt {keys['shifted[letter=a]']}: holds artifact {keys['shifted[letter=b]']}" in v.stdout
    out = run_json(toy)
    assert statuses(out)["shifted[letter=a]"] == "ran" and statuses(out)["summary"] == "cutoff"
    assert json.loads(cli(toy, "metrics", "--json").stdout)["toy/total"] == total
    assert cli(toy, "verify").returncode == 0


def test_an_edited_metric_in_an_index_record_is_not_reported(toy):
    run_json(toy)
    total = json.loads(cli(toy, "metrics", "--json").stdout)["toy/total"]
    (rec_path,) = [p for p in (toy / "artifacts" / "index").glob("*.json")
                   if json.loads(p.read_text())["instance"] == "summary"]
    rec = json.loads(rec_path.read_text())
    rec["metrics"]["toy/total"] = -7e-15
    rec_path.write_text(json.dumps(rec))
    assert json.loads(cli(toy, "metrics", "--json").stdout)["toy/total"] == total
    assert json.loads(rec_path.read_text())["metrics"]["toy/total"] == total   # rebuilt
    rec_path.write_text(json.dumps(rec))
    v = cli(toy, "verify", check=False)
    assert v.returncode == 1 and f"corrupt index/{rec_path.name}: damaged record" in v.stdout
    assert not rec_path.exists() and cli(toy, "verify").returncode == 0


def test_metrics_rebuilds_a_deleted_index_from_the_objects(toy):
    run_json(toy)
    before = json.loads(cli(toy, "metrics", "--json").stdout)
    import shutil
    shutil.rmtree(toy / "artifacts" / "index")
    assert json.loads(cli(toy, "metrics", "--json").stdout) == before
    assert len(list((toy / "artifacts" / "index").glob("*.json"))) == 6
    assert set(statuses(run_json(toy)).values()) == {"cached"}


def test_verify_refuses_an_unreadable_objects_folder_and_deletes_nothing(toy, monkeypatch, capsys):
    run_json(toy)
    objects = toy / "artifacts" / "objects"
    index = sorted(p.name for p in (toy / "artifacts" / "index").iterdir())
    real = os.scandir

    def scandir(path="."):
        if Path(path).resolve() == objects.resolve():
            raise PermissionError(13, "Permission denied", str(path))
        return real(path)
    monkeypatch.chdir(toy)
    monkeypatch.setattr(os, "scandir", scandir)
    assert main(["verify"]) == 2
    err = capsys.readouterr().err
    assert err == f"pipeline: error: cannot read {objects}: Permission denied (nothing was changed)\n"
    monkeypatch.undo()
    assert sorted(p.name for p in (toy / "artifacts" / "index").iterdir()) == index


@pytest.fixture
def small_disk(tmp_path):
    """A 2 MiB tmpfs (needs the right to mount: root in a container)."""
    mnt = tmp_path / "disk"
    mnt.mkdir()
    p = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=2m", "tmpfs", str(mnt)], capture_output=True)
    if p.returncode:
        pytest.skip("cannot mount a tmpfs here (test_store simulates the full disk instead)")
    yield mnt
    subprocess.run(["umount", str(mnt)], check=True)


def test_a_full_disk_is_one_line_and_damages_nothing(toy, small_disk):
    """On a real 2 MiB disk: a 4.8 MB artifact fails with one line, exit 2 (it segfaulted, rc 139,
    after h5py's errors), its temp file is gone, and what the store held is intact."""
    store = small_disk / "store"
    first = run_json(toy, "--store", str(store))
    p = cli(toy, "run", "--store", str(store), "-p", "size=400000", check=False)
    assert p.returncode == 2 and p.stdout == "" and p.stderr.count("\n") == 1, p.stderr[-3000:]
    assert p.stderr.startswith(f"pipeline: error: node base: store full: ") and "Traceback" not in p.stderr
    free, need = (int(v) for v in re.match(r".*store full: (\d+) bytes free on " + re.escape(str(small_disk))
                                             + r" \(tmpfs\), need about (\d+)$", p.stderr.strip()).groups())
    assert 0 < free < 2 * 2**20 < need
    assert not [q for q in (store / "objects").iterdir() if q.name.startswith(".")]
    assert cli(toy, "verify", "--store", str(store)).returncode == 0
    assert set(statuses(run_json(toy, "--store", str(store))).values()) == {"cached"}
    assert len(first["nodes"]) == len(list((store / "objects").glob("*.h5")))


def test_gc_names_the_command_that_clears_an_unreadable_artifact(toy):
    """Before: its hint said `pipeline verify` moves the file aside; it does not, and gc
    refused again after any number of verifies."""
    first = run_json(toy)
    key = next(n["key"] for n in first["nodes"] if n["name"] == "shifted[letter=a]")
    path = toy / "artifacts" / "objects" / f"{key}.h5"
    path.write_bytes(b"not an HDF5 file" * 64)          # unreadable, and its record ...
    (toy / "artifacts" / "index" / f"{key}.json").unlink()   # ... gone: gc must read the file
    p = cli(toy, "gc", check=False)
    assert p.returncode == 2 and p.stderr.count("\n") == 1
    assert f"a `pipeline run` that needs it moves it aside and recomputes it, or remove {path}" in p.stderr
    cli(toy, "verify", check=False)
    assert cli(toy, "gc", check=False).returncode == 2            # verify does not clear it
    run_json(toy)                                                 # the command the hint names
    assert cli(toy, "gc").returncode == 0
