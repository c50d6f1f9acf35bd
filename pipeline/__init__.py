"""A small content-addressed pipeline engine: DAG of pure functions, HDF5 store, CLI.

The engine knows nothing of the science it runs; a project names its graph in
pyproject.toml (`[tool.pipeline] graph = "module:ATTR"`).
"""
from pipeline.errors import PipelineError
from pipeline.graph import Graph, Listing, Node, Wiring

__all__ = ["Graph", "Listing", "Node", "PipelineError", "Wiring"]
