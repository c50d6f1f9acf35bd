"""Every node of the project's graph can be called as the scheduler calls it."""
import importlib
import inspect

import pytest

from stages.graph import GRAPH


@pytest.mark.parametrize("name", sorted(GRAPH.nodes))
def test_node_function_takes_its_inputs_params_and_grid_values(name):
    """The scheduler passes a node's inputs, params (but its Wiring, which only choose inputs)
    and grid variables by name: the function must accept each of them and need no other (but
    `staging_dir` and `checkpoint`, which the worker gives the functions that ask for them)."""
    from pipeline import Wiring
    node = GRAPH.nodes[name]
    module, _, attr = node.func.partition(":")
    sig = inspect.signature(getattr(importlib.import_module(module), attr))
    given = {*node.inputs, *(k for k, v in node.params.items() if not isinstance(v, Wiring)), *node.grid_vars}
    supplied = given | {"staging_dir", "checkpoint"}
    takes = {p.name for p in sig.parameters.values()
             if p.kind in (p.POSITIONAL_OR_KEYWORD, p.KEYWORD_ONLY)}
    if not any(p.kind is p.VAR_KEYWORD for p in sig.parameters.values()):
        assert given <= takes, f"{node.func} does not take {sorted(given - takes)}"
    needed = {p.name for p in sig.parameters.values()
              if p.default is p.empty and p.kind in (p.POSITIONAL_OR_KEYWORD, p.KEYWORD_ONLY)}
    assert needed <= supplied, f"{node.func} needs {sorted(needed - supplied)}, which the graph does not give"
