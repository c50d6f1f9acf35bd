"""Finding the project: pyproject.toml's [tool.pipeline] names the graph and params."""
from __future__ import annotations

import importlib
import os
import sys
import tomllib
from dataclasses import dataclass
from pathlib import Path

from pipeline.errors import PipelineError
from pipeline.graph import Graph


@dataclass
class Project:
    root: Path
    graph_ref: str
    params_file: Path
    profiles_dir: Path
    store_dir: Path
    source_roots: list[Path]
    ranges_file: Path | None = None   # the params' allowed values (pipeline.ranges)
    node_context: str | None = None   # "module:function", a context manager every node runs in

    def load_graph(self) -> Graph:
        module, _, attr = self.graph_ref.partition(":")
        root = str(self.root)
        if root not in sys.path:
            sys.path.insert(0, root)
        try:
            graph = getattr(importlib.import_module(module), attr or "GRAPH")
        except (ImportError, AttributeError) as exc:
            raise PipelineError(f"cannot load graph '{self.graph_ref}': {exc}") from None
        if not isinstance(graph, Graph):
            raise PipelineError(f"'{self.graph_ref}' is a {type(graph).__name__}, not a pipeline Graph")
        return graph


def find_project(start: Path | None = None) -> Project:
    """The nearest enclosing directory whose pyproject.toml has a [tool.pipeline] table."""
    env = os.environ.get("PIPELINE_PROJECT")
    here = Path(env or start or Path.cwd()).resolve()
    for d in [here, *here.parents]:
        f = d / "pyproject.toml"
        if not f.is_file():
            continue
        try:
            conf = tomllib.loads(f.read_text()).get("tool", {}).get("pipeline")
        except tomllib.TOMLDecodeError as exc:
            raise PipelineError(f"malformed {f}: {exc}") from None
        if conf is None:
            continue
        if "graph" not in conf:
            raise PipelineError(f"{f}: [tool.pipeline] needs graph = \"module:ATTR\"")
        return Project(
            root=d,
            graph_ref=conf["graph"],
            params_file=d / conf.get("params", "params.yaml"),
            profiles_dir=d / conf.get("profiles", "params"),
            store_dir=d / conf.get("store", "artifacts"),
            source_roots=[d / r for r in conf.get("source_roots", ["."])],
            ranges_file=d / conf["ranges"] if conf.get("ranges") else None,
            node_context=conf.get("node_context") or None,
        )
    raise PipelineError(f"no pyproject.toml with a [tool.pipeline] table in {here} or above")
