"""Fan-out, instance names, input references and target selection."""
import pytest

from pipeline.errors import PipelineError
from pipeline.graph import Graph

PARAMS = {"sensors": ["gs-a", "gs-b", "tactip"], "pairs": {"src": ["gs-a"], "tgt": ["gs-b", "tactip"]},
          "cfg": {"gs-a": {"size": 1}, "gs-b": {"size": 2}, "tactip": {"size": 3}}}


def graph():
    g = Graph()
    g.node("meshes", "m:f")
    g.node("render", "m:r", inputs={"meshes": "meshes"}, params={"cfg": "cfg.{sensor}"},
           grid={"sensor": "sensors"})
    g.node("translate", "m:t", inputs={"src": "render[sensor={source}]", "tgt": "render[sensor={target}]"},
           grid={"source": "pairs.src", "target": "pairs.tgt"})
    g.node("fid", "m:k", inputs={"images": "render"}, grid={"sensor": "sensors"})
    g.node("table", "m:s", inputs={"all": "translate[source=gs-a]", "every": "render[*]"})
    return g


def test_expansion_names_and_inputs():
    inst = graph().expand(PARAMS)
    assert list(inst)[:4] == ["meshes", "render[sensor=gs-a]", "render[sensor=gs-b]", "render[sensor=tactip]"]
    t = inst["translate[source=gs-a,target=tactip]"]
    assert t.inputs == {"src": "render[sensor=gs-a]", "tgt": "render[sensor=tactip]"}
    assert inst["render[sensor=gs-b]"].params == {"cfg": {"size": 2}}
    assert inst["render[sensor=gs-b]"].param_keys == ["cfg.gs-b", "sensors"]
    assert inst["fid[sensor=tactip]"].inputs == {"images": "render[sensor=tactip]"}
    table = inst["table"]
    assert table.inputs["all"] == {"gs-b": "translate[source=gs-a,target=gs-b]",
                                   "tactip": "translate[source=gs-a,target=tactip]"}
    assert list(table.inputs["every"]) == ["gs-a", "gs-b", "tactip"]
    assert len(inst) == 1 + 3 + 2 + 3 + 1


def test_select_and_closure():
    g = graph()
    inst = g.expand(PARAMS)
    assert g.select(inst, ["render[sensor=gs-b]"]) == ["render[sensor=gs-b]"]
    assert g.select(inst, ["translate[target=tactip]"]) == ["translate[source=gs-a,target=tactip]"]
    assert len(g.select(inst, ["render"])) == 3
    assert g.select(inst, None) == ["fid[sensor=gs-a]", "fid[sensor=gs-b]", "fid[sensor=tactip]", "table"]
    assert g.closure(inst, ["translate[source=gs-a,target=gs-b]"]) == [
        "meshes", "render[sensor=gs-a]", "render[sensor=gs-b]", "translate[source=gs-a,target=gs-b]"]


@pytest.mark.parametrize("target,message", [
    ("rendr", r"unknown target 'rendr'; did you mean 'render'\?"),
    ("render[senzor=gs-a]", r"node 'render' has no grid variable \['senzor'\]"),
    ("render[sensor=nope]", r"no instance of 'render' has those values"),
    ("render[sensor", r"malformed target"),
    ("render[sensor=]", r"malformed selector"),
])
def test_bad_targets(target, message):
    g = graph()
    with pytest.raises(PipelineError, match=message):
        g.select(g.expand(PARAMS), [target])


def test_graph_errors():
    g = Graph()
    g.node("a", "m:a", inputs={"x": "b"})
    g.node("b", "m:b", inputs={"y": "a"})
    with pytest.raises(PipelineError, match="cycle in graph: a -> b -> a"):
        g.expand({})
    g = Graph()
    g.node("a", "m:a", inputs={"x": "nothere"})
    with pytest.raises(PipelineError, match="names unknown node 'nothere'"):
        g.expand({})
    with pytest.raises(PipelineError, match="declared twice"):
        g.node("a", "m:a")
    with pytest.raises(PipelineError, match="func must be 'module:function'"):
        g.node("c", "m.c")
    g = Graph()
    g.node("r", "m:r", grid={"s": "sensors"})
    g.node("u", "m:u", inputs={"x": "r"})
    with pytest.raises(PipelineError, match=r"'r' matches 3 instances; use 'r\[var=...\]' or 'r\[\*\]'"):
        g.expand(PARAMS)
