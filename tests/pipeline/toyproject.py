"""A small project on disk for engine tests: its own pyproject, params and graph."""
from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path
import json

PYPROJECT = """\
[tool.pipeline]
graph = "toy.graph:GRAPH"
"""

PARAMS = """\
seed: 3
scale: 2.0
size: 16
letters: [a, b]
offset: {a: 1.0, b: 5.0}
slow: 0.0
"""

GRAPH = '''\
from pipeline import Graph

GRAPH = Graph()
GRAPH.node("base", "toy.nodes:make_base", params={"seed": "seed", "size": "size"})
GRAPH.node("scaled", "toy.nodes:scale", inputs={"base": "base"}, params={"scale": "scale"})
GRAPH.node("shifted", "toy.nodes:shift", inputs={"scaled": "scaled"},
           params={"offset": "offset.{letter}"}, grid={"letter": "letters"})
GRAPH.node("frames", "toy.nodes:frames", inputs={"base": "base"}, params={"slow": "slow"})
GRAPH.node("summary", "toy.nodes:summary", inputs={"parts": "shifted[*]", "frames": "frames"})
'''

NODES = '''\
import os
import time
import numpy as np

from toy.helpers import normalise


def _log(name):
    # lets tests count how often each node really computed
    path = os.environ.get("TOY_LOG")
    if path:
        with open(path, "a") as f:
            f.write(name + "\\n")


def make_base(seed, size):
    _log("base")
    rng = np.random.default_rng(seed)
    return {"x": rng.normal(size=(size, 3)).astype(np.float32), "attrs": {"kind": "base"}}


def scale(base, scale):
    # a comment that does not change the code
    _log("scaled")
    return {"x": normalise(np.asarray(base["x"])) * scale}


def shift(scaled, offset, letter):
    _log(f"shifted[letter={letter}]")
    return {"x": np.asarray(scaled["x"]) + offset, "label": letter}


def frames(base, slow):
    _log("frames")
    n = len(base["x"])
    for i in range(0, 40, 8):
        if slow:
            time.sleep(slow)
        yield {"images": np.full((8, 4, 4), i, np.uint8), "t": np.arange(i, i + 8, dtype=np.float64)}
    return {"reference": np.zeros((4, 4), np.uint8), "attrs": {"n": n}}


def summary(parts, frames):
    _log("summary")
    total = sum(float(np.asarray(p["x"]).sum()) for p in parts.values())
    return {"total": np.array(total), "metrics": {"toy/total": total,
                                                  "toy/frames": float(len(frames["images"]))}}
'''

HELPERS = '''\
import numpy as np


def normalise(x):
    return (x - x.mean()) / (x.std() + 1e-9)
'''


def make(root: Path) -> Path:
    (root / "toy").mkdir(parents=True)
    (root / "pyproject.toml").write_text(PYPROJECT)
    (root / "params.yaml").write_text(PARAMS)
    (root / "params").mkdir()
    (root / "params" / "small.yaml").write_text("size: 8\n")
    (root / "toy" / "__init__.py").write_text("")
    (root / "toy" / "graph.py").write_text(GRAPH)
    (root / "toy" / "nodes.py").write_text(NODES)
    (root / "toy" / "helpers.py").write_text(HELPERS)
    return root


def cli(root: Path, *args: str, check: bool = True, env: dict | None = None, timeout: float = 120):
    """Run `python -m pipeline ARGS` in the toy project; returns the CompletedProcess."""
    e = {**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[2]), **(env or {})}
    e.pop("PIPELINE_STORE", None)
    e.pop("PIPELINE_PROJECT", None)
    p = subprocess.run([sys.executable, "-m", "pipeline", *args], cwd=root, env=e,
                       capture_output=True, text=True, timeout=timeout)
    if check and p.returncode != 0:
        raise AssertionError(f"pipeline {' '.join(args)} exited {p.returncode}:\n{p.stdout}\n{p.stderr}")
    return p


def run_json(root: Path, *args: str, **kw) -> dict:
    p = cli(root, "run", "--json", *args, **kw)
    return json.loads(p.stdout)


def statuses(out: dict) -> dict[str, str]:
    return {n["name"]: n["status"] for n in out["nodes"]}
