"""The HDF5 store: round trips, streaming, atomic publish, verification, gc, no pickles."""
import json
import os
from pathlib import Path

import h5py
import numpy as np
import pytest

from pipeline.artifact import Artifact, verify_file
from pipeline.errors import PipelineError
from pipeline.store import Store
from tests.helpers import data_offset


def write(store, key, **datasets):
    w = store.writer(key, {"node": "n", "instance": "n", "key": key, "inputs": {}})
    for name, value in datasets.items():
        w.put(name, value)
    return w.commit()


def test_round_trip_and_record(tmp_path):
    store = Store(tmp_path).init()
    w = store.writer("k1", {"node": "n", "instance": "n[a=1]", "key": "k1", "inputs": {}})
    w.put("force", np.arange(6, dtype=np.float32).reshape(2, 3))
    w.put("names", ["cone", "sphere"])
    w.put("model/conv.weight", np.ones((2, 2)))
    w.put("scalar", np.float64(2.5))
    for i in range(3):
        w.append("images", np.full((4, 5, 5), i, np.uint8))
    w.set_attrs({"backend": "scalar_rgb", "size": 64, "ratios": [1.0, 2.0],
                 "config": {"width": 16, "mults": [1, 2]}, "skins": ["a", "b"], "note": '{"x": 1}'})
    w.metrics["x/mae"] = 0.25
    rec = w.commit()
    assert rec["instance"] == "n[a=1]" and rec["bytes"] == os.path.getsize(store.path("k1"))
    assert store.record("k1")["digest"] == rec["digest"]
    with Artifact(store.path("k1")) as a:
        assert sorted(a) == ["force", "images", "model/conv.weight", "names", "scalar"]
        assert "model/conv.weight" in a and "model" not in a and "nope" not in a and len(a) == 5
        with pytest.raises(KeyError, match=r"'model' not in artifact k1.h5 \(has \['force', 'images', "
                                           r"'model/conv.weight', 'names', 'scalar'\]\)"):
            a["model"]          # a group, not a dataset
        assert a["images"].shape == (12, 5, 5) and a["images"][4:8].max() == 1
        assert np.asarray(a["force"]).tolist() == [[0, 1, 2], [3, 4, 5]]
        assert list(a["names"][()]) == ["cone", "sphere"]
        assert a["scalar"][()] == 2.5 and a["scalar"].shape == ()
        assert np.asarray(a["scalar"]).shape == () and float(np.asarray(a["scalar"])) == 2.5
        assert a.attrs == {"backend": "scalar_rgb", "size": 64, "ratios": [1.0, 2.0],  # nested: JSON
                           "config": {"width": 16, "mults": [1, 2]}, "skins": ["a", "b"], "note": '{"x": 1}'}
        assert a.metrics == {"x/mae": 0.25}
        assert a.provenance["digest"] == rec["digest"]
    assert verify_file(store.path("k1")) == (True, "ok")


def test_streamed_and_whole_writes_have_the_same_digest(tmp_path):
    store = Store(tmp_path).init()
    x = np.random.default_rng(0).integers(0, 255, (300, 32, 32), dtype=np.uint8)
    whole = write(store, "a", images=x)
    w = store.writer("b", {"node": "n", "instance": "n", "key": "b", "inputs": {}})
    for i in range(0, 300, 7):
        w.append("images", x[i:i + 7])
    assert w.commit()["digest"] == whole["digest"]


@pytest.mark.parametrize("value,message", [
    (np.array([object(), 1], dtype=object), "unsupported dtype object"),
    (np.array(["2020-01-01"], dtype="datetime64[D]"), "unsupported dtype datetime64"),
])
def test_no_pickles_or_odd_dtypes(tmp_path, value, message):
    store = Store(tmp_path).init()
    w = store.writer("k", {"node": "n", "instance": "n", "key": "k", "inputs": {}})
    with pytest.raises(PipelineError, match=message):
        w.put("x", value)
    w.abort()
    assert not list((tmp_path / "objects").glob("*"))


def test_mismatched_chunks_rejected(tmp_path):
    w = Store(tmp_path).init().writer("k", {"node": "n", "instance": "n", "key": "k", "inputs": {}})
    w.append("x", np.zeros((2, 3), np.float32))
    with pytest.raises(PipelineError, match=r"chunk float64\(3,\) does not match earlier chunks float32\(3,\)"):
        w.append("x", np.zeros((2, 3), np.float64))
    w.abort()


def test_abort_leaves_nothing(tmp_path):
    store = Store(tmp_path).init()
    w = store.writer("k", {"node": "n", "instance": "n", "key": "k", "inputs": {}})
    w.put("x", np.zeros(3))
    w.abort()
    assert store.record("k") is None and not list(store.objects.iterdir())


def _flip_data_byte(path, name):
    with h5py.File(path, "r") as f:
        offset = data_offset(f[name])
    with open(path, "r+b") as fh:
        fh.seek(offset + 3)
        b = fh.read(1)
        fh.seek(offset + 3)
        fh.write(bytes([b[0] ^ 0xFF]))


def test_flipped_byte_is_detected_and_quarantined(tmp_path):
    store = Store(tmp_path).init()
    write(store, "k", x=np.arange(10, dtype=np.float64))
    st = os.stat(store.path("k"))
    _flip_data_byte(store.path("k"), "x")
    os.utime(store.path("k"), ns=(st.st_atime_ns, st.st_mtime_ns))  # hide it from stat checks
    assert store.record("k") is not None  # the fast path cannot see it...
    bad = store.verify()
    # ...verify can: the chunk's Fletcher32 checksum fails its read before any digest is taken
    assert [k for k, _ in bad] == ["k"] and "filter returned failure during read" in bad[0][1]
    os.utime(store.path("k"))  # a changed mtime sends record() to the content check
    assert store.record("k") is None
    assert not store.path("k").exists() and len(list(store.corrupt.glob("k-*.h5"))) == 1


def test_truncated_file_is_detected(tmp_path):
    store = Store(tmp_path).init()
    write(store, "k", x=np.arange(10000, dtype=np.float64))
    with open(store.path("k"), "r+b") as fh:
        fh.truncate(os.path.getsize(store.path("k")) // 2)
    ok, message = verify_file(store.path("k"))
    assert not ok and message.startswith("unreadable")
    assert store.record("k") is None


def test_missing_index_is_rebuilt_from_the_artifact(tmp_path):
    store = Store(tmp_path).init()
    rec = write(store, "k", x=np.arange(4))
    (store.index / "k.json").unlink()  # as after a crash between publish and index write
    again = store.record("k")
    assert again["digest"] == rec["digest"] and json.loads((store.index / "k.json").read_text())["key"] == "k"


def test_gc_keeps_refs_recent_runs_and_their_inputs(tmp_path):
    store = Store(tmp_path).init()
    for k in ("a", "b", "c", "d"):
        write(store, k, x=np.arange(3))
    rec = json.loads((store.index / "b.json").read_text())
    rec["inputs"] = {"up": "c"}
    store.write_record(rec)
    store.write_ref("node_b", {"key": "b"})
    import socket
    host = socket.gethostname()
    dead = store.objects / f".tmp-z-999999-abc-{host}.h5"       # a dead writer on this host
    dead.write_bytes(b"partial")
    live = store.objects / f".tmp-y-{os.getpid()}-abc-{host}.h5"  # this process: alive
    live.write_bytes(b"partial")
    remote = store.objects / ".tmp-x-1-abc-otherhost.h5"          # another host: kept a day
    remote.write_bytes(b"partial")
    old = store.objects / ".tmp-w-1-abc-otherhost.h5"
    old.write_bytes(b"partial")
    os.utime(old, (0, 0))
    assert store.gc(set(), dry_run=True) == ["a", "d"]
    assert store.path("a").exists()
    assert store.gc({"d"}) == ["a"]
    assert [p.stem for p in store.object_paths()] == ["b", "c", "d"]
    assert not dead.exists() and not old.exists() and live.exists() and remote.exists()


def test_find_by_key_prefix(tmp_path):
    store = Store(tmp_path).init()
    write(store, "abcdef0123", x=np.arange(2))
    write(store, "abcdef9999", x=np.arange(3))
    assert store.find("abcdef01")["key"] == "abcdef0123"
    with pytest.raises(PipelineError, match="ambiguous"):
        store.find("abcdef")
    with pytest.raises(PipelineError, match="no artifact with key 'zzz'"):
        store.find("zzz")


STREAM_SCRIPT = """
import resource, sys
import numpy as np
from pipeline.store import Store
n = int(sys.argv[2])
w = Store(sys.argv[1]).init().writer("k", {"node": "n", "instance": "n", "key": "k", "inputs": {}})
rng = np.random.default_rng(0)
for i in range(n):
    w.append("images", rng.integers(0, 255, (16, 256, 256), dtype=np.uint8))  # 1 MiB, incompressible
w.commit()
print(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss)
"""


def test_streamed_writes_use_constant_memory(tmp_path):
    import subprocess
    import sys
    rss = {}
    for n in (20, 400):  # 20 MiB vs 400 MiB of frames
        p = subprocess.run([sys.executable, "-c", STREAM_SCRIPT, str(tmp_path / f"s{n}"), str(n)],
                           capture_output=True, text=True, check=True,
                           env={**os.environ, "PYTHONPATH": str(Path(__file__).parents[2])})
        rss[n] = int(p.stdout.split()[-1]) / 1024  # MiB
    assert rss[400] - rss[20] < 40, rss  # 380 MiB more data, (almost) no more memory


def test_reused_buffer_and_mixed_chunk_sizes_digest_correctly(tmp_path):
    store = Store(tmp_path).init()
    w = store.writer("k", {"node": "n", "instance": "n", "key": "k", "inputs": {}})
    buf = np.empty((8, 128, 128), np.uint8)  # 128 KiB, refilled for every chunk
    for j in range(10):
        buf[:] = j
        w.append("images", buf)
    w.append("images", np.full((1, 128, 128), 99, np.uint8))  # a small last chunk
    w.commit()
    assert verify_file(store.path("k")) == (True, "ok")
    with Artifact(store.path("k")) as a:
        assert [int(a["images"][i * 8, 0, 0]) for i in range(10)] == list(range(10))


def test_large_chunks_digested_while_written_match_small_ones(tmp_path):
    """Chunks of OVERLAP_BYTES or more are hashed in a thread while HDF5 writes them: the
    digest must equal the one-thread digest of the same data, even from a reused buffer."""
    from pipeline import artifact
    store = Store(tmp_path).init()
    x = np.random.default_rng(3).integers(0, 255, (48, 256, 256), dtype=np.uint8)  # 3 MiB
    w = store.writer("big", {"node": "n", "instance": "n", "key": "big", "inputs": {}})
    buf = np.empty((16, 256, 256), np.uint8)  # 1 MiB: overlapped
    assert buf.nbytes >= artifact.OVERLAP_BYTES
    for i in range(0, 48, 16):
        buf[:] = x[i:i + 16]
        w.append("images", buf)
    w.put("whole", x)
    big = w.commit()
    w = store.writer("small", {"node": "n", "instance": "n", "key": "small", "inputs": {}})
    for i in range(48):  # 64 KiB chunks: hashed in the caller's thread
        w.append("images", x[i:i + 1])
    w.put("whole", x.copy())
    assert w.commit()["digest"] == big["digest"]
    assert verify_file(store.path("big")) == (True, "ok")


def test_a_failing_digest_thread_fails_the_write(tmp_path, monkeypatch):
    store = Store(tmp_path).init()
    w = store.writer("k", {"node": "n", "instance": "n", "key": "k", "inputs": {}})

    def broken(*args, **kwargs):
        raise MemoryError("digest thread ran out")
    monkeypatch.setattr(w.digest, "update", broken)
    with pytest.raises(MemoryError, match="digest thread ran out"):
        w.append("images", np.zeros((32, 256, 256), np.uint8))
    w.abort()
    assert not store.path("k").exists()


def test_unicode_strings_round_trip(tmp_path):
    store = Store(tmp_path).init()
    write(store, "k", names=["bé", "Ω-pad"], label="tactip-é")
    with Artifact(store.path("k")) as a:
        assert list(a["names"][()]) == ["bé", "Ω-pad"] and a["label"][()] == "tactip-é"
        assert [list(c) for c in a["names"].iter_chunks(1)] == [["bé"], ["Ω-pad"]]
    assert verify_file(store.path("k")) == (True, "ok")


# -- trust: a file belongs to the key in its name; bookkeeping files carry a check -----------

def test_a_file_copied_over_another_keys_path_is_rejected(tmp_path):
    """Both files are intact, so only the key each carries tells the copy does not belong."""
    import shutil
    store = Store(tmp_path).init()
    write(store, "a", x=np.arange(10, dtype=np.float64))
    write(store, "b", x=np.arange(10, dtype=np.float64) + 1)
    shutil.copyfile(store.path("b"), store.path("a"))
    assert verify_file(store.path("a")) == (False, "holds artifact b, not a (copied or moved over it)")
    assert store.verify() == [("a", "holds artifact b, not a (copied or moved over it)")]
    assert store.record("a") is None                  # changed file: content check, moved aside
    assert not store.path("a").exists() and len(list(store.corrupt.glob("a-*.h5"))) == 1


def test_reading_a_file_of_another_key_with_a_matching_record_is_refused(tmp_path):
    """Size and mtime agree with the record (the fast path passes): opening it as an input
    still checks the key it carries."""
    import shutil
    store = Store(tmp_path).init()
    rec = write(store, "a", x=np.arange(10, dtype=np.float64))
    write(store, "b", x=np.arange(10, dtype=np.float64) + 1)
    shutil.copyfile(store.path("b"), store.path("a"))
    st = store.path("a").stat()
    store.write_record({**rec, "bytes": st.st_size, "mtime_ns": st.st_mtime_ns})
    assert store.record("a") is not None
    with pytest.raises(PipelineError, match=r"^input 'x' of n: artifact a is corrupt \(holds artifact b, not a "
                                            r"\(copied or moved over it\)\); moved to corrupt/a-"):
        store.open("a", "input 'x' of n")
    with store.open("b", "input 'x' of n") as art:
        assert np.asarray(art["x"])[0] == 1.0


@pytest.mark.parametrize("edit", ["metric", "digest", "bytes"])
def test_an_edited_index_record_is_rebuilt_from_its_artifact(tmp_path, edit):
    store = Store(tmp_path).init()
    w = store.writer("k", {"node": "n", "instance": "n", "inputs": {}})
    w.put("x", np.arange(3))
    w.metrics["m/fid"] = 2.5
    rec = w.commit()
    path = store.index / "k.json"
    doc = json.loads(path.read_text())
    doc.update({"metric": {"metrics": {"m/fid": -7e-15}}, "digest": {"digest": "0" * 64},
                "bytes": {"bytes": doc["bytes"] + 1}}[edit])
    path.write_text(json.dumps(doc))
    assert store.verify() == [("index/k.json", "damaged record: its content does not match its check")]
    again = store.record("k")
    assert again["metrics"] == {"m/fid": 2.5} and again["digest"] == rec["digest"]
    assert json.loads(path.read_text())["metrics"] == {"m/fid": 2.5} and store.verify() == []
    assert [r["metrics"] for r in store.records()] == [{"m/fid": 2.5}]


def test_verify_checks_refs_and_run_logs(tmp_path):
    store = Store(tmp_path).init()
    write(store, "a", x=np.arange(3))
    store.write_ref("n", {"key": "a", "digest": "d"})
    store.log_run(["a"], {"targets": []})
    assert store.verify() == []
    ref = store.refs / "n.json"
    ref.write_text(ref.read_text().replace('"key": "a"', '"key": "b"'))
    (run,) = store.runs.glob("*.json")
    run.write_text(run.read_text().replace('"a"', '"c"'))
    assert store.verify() == [("refs/n.json", "damaged ref: not a ref, or its content does not match its check"),
                              (f"runs/{run.name}",
                               "damaged run log: not a run log, or its content does not match its check")]
    assert store.read_ref("n") is None                   # status reads it as missing
    with pytest.raises(PipelineError, match=r"gc: .*refs/n\.json is damaged.*nothing was removed"):
        store.gc(set())
    assert store.path("a").exists()


@pytest.mark.parametrize("folder", ["objects", "index", "refs", "runs"])
def test_an_unreadable_store_folder_stops_verify_and_gc(tmp_path, monkeypatch, folder):
    """Read as empty, an unreadable runs/ or refs/ made gc delete what their files keep, and
    an unreadable objects/ made verify call every artifact missing."""
    store = Store(tmp_path).init()
    write(store, "a", x=np.arange(3))
    write(store, "b", x=np.arange(4))
    store.log_run(["a"], {"targets": []})
    store.write_ref("n", {"key": "b"})
    real = os.scandir

    def scandir(path="."):
        if Path(path) == tmp_path / folder:
            raise PermissionError(13, "Permission denied", str(path))
        return real(path)
    monkeypatch.setattr(os, "scandir", scandir)
    message = rf"^cannot read {tmp_path / folder}: Permission denied \(nothing was changed\)$"
    with pytest.raises(PipelineError, match=message):
        store.verify()
    with pytest.raises(PipelineError, match=message):
        store.gc(set())
    monkeypatch.undo()
    assert sorted(p.name for p in store.index.iterdir()) == ["a.json", "b.json"]
    assert [p.stem for p in store.object_paths()] == ["a", "b"]


def test_gc_keeps_the_inputs_of_a_kept_artifact_whose_record_is_damaged(tmp_path):
    store = Store(tmp_path).init()
    write(store, "c", x=np.arange(3))
    w = store.writer("b", {"node": "n", "instance": "n", "inputs": {"up": "c"}})
    w.put("x", np.arange(3))
    w.commit()
    (store.index / "b.json").write_text("{}")
    assert store.gc({"b"}) == []
    assert store.path("c").exists()


FULL_SCRIPT = """
import errno, sys
import numpy as np
from pipeline import artifact
from pipeline.space import StoreFull
from pipeline.store import Store
budget = [int(sys.argv[2])]
real = artifact._TempFile._write

def write(self, view):                    # a disk with `budget` bytes left
    if len(view) > budget[0]:
        raise OSError(errno.ENOSPC, "No space left on device")
    budget[0] -= len(view)
    return real(self, view)
store = Store(sys.argv[1]).init()
w = store.writer("a", {"node": "n", "instance": "n", "inputs": {}})
w.put("x", np.arange(10))
w.commit()
artifact._TempFile._write = write
w = store.writer("b", {"node": "n", "instance": "n", "inputs": {}})
rng = np.random.default_rng(0)
try:
    for i in range(50):
        w.append("images", rng.integers(0, 255, (16, 64, 64), dtype=np.uint8))
    w.commit()
except StoreFull as exc:
    w.abort()
    print(exc)
"""


def test_a_disk_full_while_writing_is_one_error_and_leaves_only_what_was_there(tmp_path):
    """HDF5 never sees the failed write (after one it can neither flush nor close its file and
    crashes the process at exit, rc 139): one StoreFull, the temp file deleted, a clean exit."""
    import subprocess
    import sys
    p = subprocess.run([sys.executable, "-c", FULL_SCRIPT, str(tmp_path), str(300_000)], capture_output=True,
                       text=True, env={**os.environ, "PYTHONPATH": str(Path(__file__).parents[2])}, timeout=120)
    assert p.returncode == 0 and p.stderr == "", p.stderr[-2000:]
    import re
    m = re.fullmatch(r"store full: (\d+) bytes free on (.+), need about (\d+)\n", p.stdout)
    assert m and int(m.group(3)) > 300_000, p.stdout          # at least what it had reached
    store = Store(tmp_path)
    assert [q.name for q in store.objects.iterdir()] == ["a.h5"] and store.verify() == []
