"""Engine benchmarks, each a ratio measured side by side in one run.

1. no-op `pipeline run` on a 100-node synthetic DAG vs no-op `dvc repro` on the dvc.yaml
   exported from the same DAG (target <= 0.2)
2. store write and read throughput vs bare h5py on the same arrays, chunks and compression
   without checksums, as the store wrote them before (target >= 0.7); and what the store's
   Fletcher32 checksums cost, bare h5py with them against bare h5py without
3. scheduling overhead per trivial node over 1000 nodes (target <= 5 ms/node), printed beside
   the floor bare h5py sets on the same machine (each node's HDF5 create + fsync and its
   inputs' opens), which is most of it

Run: .venv/bin/python benchmarks/engine.py [--quick]
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from benchmarks.summary import record  # noqa: E402


def synthetic_project(root: Path, n_nodes: int, modules: int = 5) -> Path:
    """n_nodes in layers of 10; each node reads up to two nodes of the layer before."""
    pkg = root / "synth"
    pkg.mkdir(parents=True)
    (root / "pyproject.toml").write_text('[tool.pipeline]\ngraph = "synth.graph:GRAPH"\n')
    (root / "params.yaml").write_text("".join(f"p{i}: {i}\n" for i in range(n_nodes)))
    (pkg / "__init__.py").write_text("")
    per = -(-n_nodes // modules)
    for m in range(modules):
        funcs = "".join(
            f"\n\ndef f{i}(p, **inputs):\n    acc = np.float64(p)\n"
            f"    for a in inputs.values():\n        acc += np.asarray(a['x']).sum()\n"
            f"    return {{'x': np.array([acc])}}\n"
            for i in range(m * per, min(n_nodes, (m + 1) * per)))
        (pkg / f"mod{m}.py").write_text("import numpy as np\n" + funcs)
    lines = ["from pipeline import Graph", "GRAPH = Graph()"]
    for i in range(n_nodes):
        ups = _upstream(i)
        inputs = {f"u{j}": f"n{j}" for j in ups}
        lines.append(f"GRAPH.node('n{i}', 'synth.mod{i // per}:f{i}', inputs={inputs!r}, params={{'p': 'p{i}'}})")
    (pkg / "graph.py").write_text("\n".join(lines) + "\n")
    return root


def _upstream(i: int) -> list[int]:
    """The synthetic DAG's inputs of node i: up to two nodes of the layer before."""
    return [j for j in (i - 10, i - 9) if j >= 0 and (j // 10) == (i // 10) - 1]


def env() -> dict:
    bin_dir = str(Path(sys.executable).parent)
    return {**os.environ, "PYTHONPATH": str(REPO), "PATH": bin_dir + os.pathsep + os.environ["PATH"]}


def timed(cmd: list[str], cwd: Path, repeat: int) -> float:
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        subprocess.run(cmd, cwd=cwd, env=env(), check=True, capture_output=True)
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def bench_noop(tmp: Path, repeat: int) -> dict:
    root = synthetic_project(tmp / "noop", 100)
    pipe = [sys.executable, "-m", "pipeline"]
    subprocess.run(pipe + ["run"], cwd=root, env=env(), check=True, capture_output=True)
    subprocess.run(pipe + ["dvc"], cwd=root, env=env(), check=True, capture_output=True)
    dvc = [sys.executable, "-m", "dvc"]
    subprocess.run(dvc + ["init", "--no-scm", "-q"], cwd=root, env=env(), check=True)
    # record dvc.lock for the outputs our run made, instead of re-running 100 stages
    subprocess.run(dvc + ["commit", "-f", "-q"], cwd=root, env=env(), check=True, capture_output=True)
    status = subprocess.run(dvc + ["status"], cwd=root, env=env(), capture_output=True, text=True)
    assert "up to date" in status.stdout, status.stdout
    ours = timed(pipe + ["run"], root, repeat)
    theirs = timed(dvc + ["repro"], root, max(2, repeat // 2))
    out = json.loads(subprocess.run(pipe + ["run", "--json"], cwd=root, env=env(), check=True,
                                    capture_output=True, text=True).stdout)
    assert {n["status"] for n in out["nodes"]} == {"cached"} and len(out["nodes"]) == 100
    return {"pipeline_s": ours, "dvc_s": theirs, "ratio": ours / theirs}


def marker_frames(n: int, size: int, seed: int = 0) -> np.ndarray:
    """Binary marker-like images (white dots on black), as the pipeline stores them."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:size, 0:size]
    base = ((np.sin(xx / 3.0) > 0.7) & (np.sin(yy / 3.0) > 0.7))
    out = np.empty((n, size, size), np.uint8)
    for i in range(n):
        dx, dy = rng.integers(-2, 3, 2)
        out[i] = np.roll(base, (dy, dx), (0, 1)) * 255
    return out


def bench_store(tmp: Path, n_frames: int, repeat: int) -> dict:
    import h5py

    from pipeline.artifact import CHUNK_BYTES, Artifact
    from pipeline.store import Store

    frames = marker_frames(n_frames, 256)
    force = np.random.default_rng(1).normal(size=(n_frames, 3)).astype(np.float32)
    step = 64
    row = frames[0:1].nbytes
    rows = max(1, min(4096, CHUNK_BYTES // row))
    mb = (frames.nbytes + force.nbytes) / 1e6

    def ours_write(i):
        store = Store(tmp / f"store{i}").init()
        w = store.writer("k", {"node": "b", "instance": "b", "key": "k", "inputs": {}})
        for s in range(0, n_frames, step):
            w.append("images", frames[s:s + step])
            w.append("force", force[s:s + step])
        w.commit()
        return store.path("k")

    def bare_write(i, checksum=False):
        path = tmp / f"bare{i}{'-f32' if checksum else ''}.h5"
        f32 = {"fletcher32": True} if checksum else {}
        with h5py.File(path, "w") as f:
            d1 = f.create_dataset("images", shape=(0, 256, 256), maxshape=(None, 256, 256), dtype=np.uint8,
                                  chunks=(rows, 256, 256), compression="lzf", **f32)
            d2 = f.create_dataset("force", shape=(0, 3), maxshape=(None, 3), dtype=np.float32,
                                  chunks=(4096, 3), compression="lzf", **f32)
            for s in range(0, n_frames, step):
                for d, a in ((d1, frames[s:s + step]), (d2, force[s:s + step])):
                    n = d.shape[0]
                    d.resize(n + len(a), axis=0)
                    d[n:] = a
        return path

    def ours_read(path):
        with Artifact(path) as a:
            imgs = a["images"]
            return sum(int(imgs[s:s + step][:, 0, 0].sum()) for s in range(0, len(imgs), step))

    def bare_read(path):
        with h5py.File(path, "r") as f:
            imgs = f["images"]
            return sum(int(imgs[s:s + step][:, 0, 0].sum()) for s in range(0, len(imgs), step))

    res = {"w_ours": [], "w_bare": [], "w_f32": [], "r_ours": [], "r_bare": [], "r_f32": []}
    for i in range(repeat):  # interleaved, so drift hits all alike
        t0 = time.perf_counter(); p_ours = ours_write(i); res["w_ours"].append(time.perf_counter() - t0)
        t0 = time.perf_counter(); p_bare = bare_write(i); res["w_bare"].append(time.perf_counter() - t0)
        t0 = time.perf_counter(); p_f32 = bare_write(i, True); res["w_f32"].append(time.perf_counter() - t0)
        t0 = time.perf_counter(); a = ours_read(p_ours); res["r_ours"].append(time.perf_counter() - t0)
        t0 = time.perf_counter(); b = bare_read(p_bare); res["r_bare"].append(time.perf_counter() - t0)
        t0 = time.perf_counter(); c = bare_read(p_f32); res["r_f32"].append(time.perf_counter() - t0)
        assert a == b == c
    med = {k: statistics.median(v) for k, v in res.items()}
    return {"MB": mb, "write_MBps_ours": mb / med["w_ours"], "write_MBps_bare": mb / med["w_bare"],
            "write_ratio": med["w_bare"] / med["w_ours"],
            "read_MBps_ours": mb / med["r_ours"], "read_MBps_bare": mb / med["r_bare"],
            "read_ratio": med["r_bare"] / med["r_ours"],
            "write_MBps_f32": mb / med["w_f32"], "write_f32_ratio": med["w_bare"] / med["w_f32"],
            "read_MBps_f32": mb / med["r_f32"], "read_f32_ratio": med["r_bare"] / med["r_f32"]}


def bench_overhead(tmp: Path, n_nodes: int) -> dict:
    root = synthetic_project(tmp / "overhead", n_nodes, modules=20)
    pipe = [sys.executable, "-m", "pipeline"]
    t0 = time.perf_counter()
    out = subprocess.run(pipe + ["run", "--json"], cwd=root, env=env(), check=True, capture_output=True, text=True)
    full = time.perf_counter() - t0
    nodes = json.loads(out.stdout)["nodes"]
    in_nodes = sum(n["seconds"] for n in nodes)  # time inside node functions + their writes
    t0 = time.perf_counter()
    subprocess.run(pipe + ["run"], cwd=root, env=env(), check=True, capture_output=True)
    noop = time.perf_counter() - t0
    reads = sum(len(_upstream(i)) for i in range(n_nodes)) / n_nodes
    return {"nodes": len(nodes), "run_s": full, "ms_per_node": 1000 * full / len(nodes),
            "ms_per_node_outside_nodes": 1000 * (full - in_nodes) / len(nodes),
            "noop_ms_per_node": 1000 * noop / len(nodes),
            "floor_ms_per_node": hdf5_floor_ms(tmp / "floor", n_nodes), "reads": reads}


def hdf5_floor_ms(folder: Path, n: int) -> float:
    """What any store with one fsync'd HDF5 file per artifact pays per trivial node of the
    synthetic DAG, with bare h5py: open node i's inputs and read their dataset, create a file
    holding one small dataset, fsync it and rename it into place."""
    import h5py
    folder.mkdir(parents=True)
    t0 = time.perf_counter()
    for i in range(n):
        for j in _upstream(i):
            with h5py.File(folder / f"{j}.h5", "r") as f:
                f["x"][()]
        tmp = folder / f".tmp{i}.h5"
        with h5py.File(tmp, "w") as f:
            f.create_dataset("x", data=np.array([float(i)]))
        fd = os.open(tmp, os.O_RDONLY)
        os.fsync(fd)
        os.close(fd)
        os.replace(tmp, folder / f"{i}.h5")
    return 1000 * (time.perf_counter() - t0) / n


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--quick", action="store_true", help="fewer repeats and smaller sizes")
    a = ap.parse_args()
    repeat = 3 if a.quick else 5
    with tempfile.TemporaryDirectory() as d:
        tmp = Path(d)
        noop = bench_noop(tmp, repeat)
        store = bench_store(tmp, 256 if a.quick else 1024, repeat)
        over = bench_overhead(tmp, 300 if a.quick else 1000)
    rows = [
        ("no-op run, 100 nodes: pipeline / dvc repro", f"{noop['pipeline_s']:.3f} s / {noop['dvc_s']:.3f} s",
         noop["ratio"], "<= 0.2"),
        ("store write: ours vs bare h5py (MB/s)", f"{store['write_MBps_ours']:.0f} / {store['write_MBps_bare']:.0f}",
         store["write_ratio"], ">= 0.7"),
        ("store read: ours vs bare h5py (MB/s)", f"{store['read_MBps_ours']:.0f} / {store['read_MBps_bare']:.0f}",
         store["read_ratio"], ">= 0.7"),
        ("  Fletcher32's cost, write: bare with / without (MB/s)",
         f"{store['write_MBps_f32']:.0f} / {store['write_MBps_bare']:.0f}", store["write_f32_ratio"], ""),
        ("  Fletcher32's cost, read: bare with / without (MB/s)",
         f"{store['read_MBps_f32']:.0f} / {store['read_MBps_bare']:.0f}", store["read_f32_ratio"], ""),
        (f"scheduling, {over['nodes']} trivial nodes (ms/node, all)", f"{over['run_s']:.2f} s total",
         over["ms_per_node"], "<= 5"),
        ("  of which outside node functions+writes (ms/node)", "", over["ms_per_node_outside_nodes"], ""),
        ("  bare h5py floor: write+fsync 1, read %.1f (ms/node)" % over["reads"], "",
         over["floor_ms_per_node"], ""),
        ("  scheduling / bare h5py floor", "", over["ms_per_node"] / over["floor_ms_per_node"], ""),
        ("  no-op re-run (ms/node)", "", over["noop_ms_per_node"], ""),
    ]
    print(f"{'benchmark':52s} {'measured':28s} {'ratio':>8s}  target")
    for name, measured, ratio, target in rows:
        print(f"{name:52s} {measured:28s} {ratio:8.3f}  {target}")
        record("engine", name.strip(), measured, ratio, target)
    print(f"(store arrays: {store['MB']:.0f} MB of 256x256 marker frames + forces, lzf, same chunks; "
          "the store's carry Fletcher32 checksums, the bare ones not)")


if __name__ == "__main__":
    main()
