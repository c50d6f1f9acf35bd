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


def test_a_node_whose_grid_is_empty_is_named_as_such():
    """A grid over an empty list (a hardware node with nothing listed yet) gives no instance:
    naming it as a target says which list is empty, and a gather of it gathers nothing."""
    g = graph()
    g.node("capture", "m:c", grid={"sensor": "captured"})
    g.node("use", "m:u", inputs={"got": "capture[*]"})
    inst = g.expand({**PARAMS, "captured": []})
    assert inst["use"].inputs == {"got": {}}
    with pytest.raises(PipelineError, match=r"unknown target 'capture': 'capture' has no instance for these "
                                            r"params \(its grid captured is empty\)"):
        g.select(inst, ["capture"])
    inst = g.expand({**PARAMS, "captured": ["gs-a"]})
    assert inst["use"].inputs == {"got": {"gs-a": "capture[sensor=gs-a]"}}
    assert g.select(inst, ["capture"]) == ["capture[sensor=gs-a]"]


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


def zipped_graph():
    g = Graph()
    g.node("markers", "m:m", grid={"skin": "skins"})
    g.node("taxels", "m:x", inputs={"m": "markers[skin={spec[like]}]"}, params={"spec": "catalogue.{skin}"},
           grid={"skin": "taxel_skins"})
    # the upstream node comes from the skin's params: a render or a taxel skin
    g.node("unify", "m:u", inputs={"source": "{spec[source]}[skin={skin}]"},
           params={"spec": "catalogue.{skin}"}, grid={"skin": "skins + taxel_skins"})
    g.node("translate", "m:t", inputs={"src": "unify[skin={source}]", "tgt": "unify[skin={target}]"},
           grid={"source,target": "homo.pairs + hetero.pairs"})
    g.node("study", "m:s", inputs={"all": "translate[*]"})
    return g


ZPARAMS = {"skins": ["a", "b"], "taxel_skins": ["u"],
           "catalogue": {"a": {"source": "markers"}, "b": {"source": "markers"}, "u": {"source": "taxels", "like": "b"}},
           "homo": {"pairs": [["a", "b"], ["b", "a"]]}, "hetero": {"pairs": [["a", "u"], ["a", "b"]]}}


def test_zipped_grid_concatenated_keys_and_params_templates():
    inst = zipped_graph().expand(ZPARAMS)
    assert inst["unify[skin=u]"].inputs == {"source": "taxels[skin=u]"}
    assert inst["taxels[skin=u]"].inputs == {"m": "markers[skin=b]"}
    assert inst["unify[skin=a]"].inputs == {"source": "markers[skin=a]"}
    assert inst["unify[skin=a]"].param_keys == ["catalogue.a", "skins", "taxel_skins"]
    pairs = [n for n in inst if n.startswith("translate")]
    # hetero's [a, b] repeats a homo pair: listed once
    assert pairs == ["translate[source=a,target=b]", "translate[source=b,target=a]",
                     "translate[source=a,target=u]"]
    assert inst["translate[source=a,target=u]"].inputs == {"src": "unify[skin=a]", "tgt": "unify[skin=u]"}
    assert list(inst["study"].inputs["all"]) == ["source=a,target=b", "source=b,target=a", "source=a,target=u"]
    # every instance comes after the instances it reads
    order = list(inst)
    for i in inst.values():
        assert all(order.index(u) < order.index(i.name) for u in i.upstream())
    g = zipped_graph()
    assert g.select(inst, ["translate[source=a]"]) == pairs[::2]


@pytest.mark.parametrize("change, message", [
    (lambda p: p["homo"].update(pairs=[["a", "b", "c"]]), "grid 'source,target': invalid value ['a', 'b', 'c']"),
    (lambda p: p["catalogue"]["a"].update(source="nowhere"), "input 'source': unknown node 'nowhere'"),
    (lambda p: p["catalogue"]["b"].pop("source"), "node 'unify[skin=b]' input 'source': template"),
    (lambda p: p.update(hetero={"pairs": "a,b"}), "grid 'source,target' (hetero.pairs) must be a list"),
])
def test_zipped_grid_and_template_errors(change, message):
    import copy
    params = copy.deepcopy(ZPARAMS)
    change(params)
    with pytest.raises(PipelineError) as err:
        zipped_graph().expand(params)
    assert message in str(err.value)


def test_empty_grid_has_no_instances_and_gathers_nothing():
    g = Graph()
    g.node("model", "m:m")
    g.node("member", "m:e", inputs={"model": "model"}, grid={"seed": "seeds"})
    g.node("use", "m:u", inputs={"model": "model", "members": "member[*]"})
    inst = g.expand({"seeds": []})
    assert list(inst) == ["model", "use"]
    assert inst["use"].inputs == {"model": "model", "members": {}}
    assert g.expand({"seeds": [1, 2]})["use"].inputs["members"] == {"1": "member[seed=1]",
                                                                     "2": "member[seed=2]"}
    # a reference that needs one instance still fails
    g.node("one", "m:o", inputs={"m": "member[seed=1]"})
    with pytest.raises(PipelineError, match=r"input 'm': no instance matches 'member\[seed=1\]'"):
        g.expand({"seeds": []})
    with pytest.raises(PipelineError, match=r"grid 'seed' \(seeds\) must be a list"):
        g.expand({"seeds": 3})


def test_a_params_list_selector_gathers_only_the_listed_instances():
    """'up[var=@key]' gathers the instances whose var is in the params list `key` (keyed by
    every such var), so the node's closure holds only those; an empty list gathers nothing
    and a key that is not a list is an error naming it."""
    g = zipped_graph()
    g.node("sim_study", "m:s", inputs={"few": "translate[source=@sims,target=@sims]",
                                       "own": "unify[skin=@sims]"})
    params = {**ZPARAMS, "sims": ["a", "b"]}
    inst = g.expand(params)
    assert inst["sim_study"].inputs == {
        "few": {"source=a,target=b": "translate[source=a,target=b]",
                "source=b,target=a": "translate[source=b,target=a]"},
        "own": {"a": "unify[skin=a]", "b": "unify[skin=b]"}}
    assert inst["sim_study"].param_keys.count("sims") == 3
    closure = g.closure(inst, ["sim_study"])
    assert "translate[source=a,target=u]" not in closure and "taxels[skin=u]" not in closure
    assert g.expand({**ZPARAMS, "sims": ["u"]})["sim_study"].inputs == {
        "few": {}, "own": {"u": "unify[skin=u]"}}
    with pytest.raises(PipelineError, match=r"input 'few': sims must be a list to select "
                                            r"translate's source, got str"):
        g.expand({**ZPARAMS, "sims": "a"})
    with pytest.raises(PipelineError, match=r"unknown param 'sims'"):
        g.expand(ZPARAMS)


# -- Listing: grid values a plan-time function lists ---------------------------------------

LISTER = '''
class Bad(ValueError):
    user_error = True

def sensors(source, root, prefix=""):
    if prefix:
        return [prefix + r for r in root.split(":")]
    if source == "none":
        return []
    if source == "bad":
        raise Bad(f"no sensors under {root}")
    if source == "crash":
        raise ZeroDivisionError("boom")
    if source == "tuple":
        return ("a",)
    return sorted(root.split(":"))
'''


@pytest.fixture()
def listing_graph(tmp_path, monkeypatch):
    from pipeline.graph import Listing
    (tmp_path / "lister_mod.py").write_text(LISTER)
    monkeypatch.syspath_prepend(str(tmp_path))
    g = Graph()
    g.node("ingest", "m:i", params={"root": "data.root"},
           grid={"sensor": Listing("lister_mod:sensors", {"source": "data.source", "root": "data.root"})})
    g.node("study", "m:s", inputs={"all": "ingest[*]"})
    return g


def test_listing_grid_lists_instances_from_params(listing_graph):
    from pipeline.graph import Listing
    inst = listing_graph.expand({"data": {"source": "authors", "root": "b:a"}})
    assert list(inst) == ["ingest[sensor=a]", "ingest[sensor=b]", "study"]
    assert inst["ingest[sensor=b]"].param_keys == ["data.root", "data.source"]
    assert inst["study"].inputs["all"] == {"a": "ingest[sensor=a]", "b": "ingest[sensor=b]"}
    none = listing_graph.expand({"data": {"source": "none", "root": ""}})
    assert list(none) == ["study"] and none["study"].inputs["all"] == {}
    g = Graph()
    g.node("pairs", "m:p", grid={"s": Listing("lister_mod:sensors", {"root": "data.root"}, {"source": "",
                                                                                       "prefix": "x"})})
    assert list(g.expand({"data": {"root": "a:b"}})) == ["pairs[s=xa]", "pairs[s=xb]"]
    with pytest.raises(PipelineError, match=r"'ingest' has no instance for these params \(its grid "
                                            r"lister_mod:sensors\(data.source, data.root\) is empty\)"):
        listing_graph.select(none, ["ingest"])


@pytest.mark.parametrize("source,message", [
    ("bad", r"^no sensors under x$"),
    ("crash", r"^node 'ingest' grid 'sensor': lister_mod:sensors failed: ZeroDivisionError: boom$"),
    ("tuple", r"^node 'ingest' grid 'sensor': lister_mod:sensors returned tuple, not a list$"),
])
def test_listing_failures_are_one_line(listing_graph, source, message):
    with pytest.raises(PipelineError, match=message):
        listing_graph.expand({"data": {"source": source, "root": "x"}})


def test_listing_must_name_an_importable_function():
    from pipeline.graph import Listing
    g = Graph()
    with pytest.raises(PipelineError, match=r"Listing func must be 'module:function', got 'nomodule'"):
        g.node("x", "m:f", grid={"s": Listing("nomodule", {})})
    g.node("y", "m:f", grid={"s": Listing("no_such_module_here:f", {})})
    with pytest.raises(PipelineError, match=r"^node 'y' grid 's': cannot import 'no_such_module_here:f': "):
        g.expand({})


# -- Wiring params, indexed templates, deferred listing errors ------------------------------

WIRER = '''
class Missing(ValueError):
    user_error = True

def where(mode):
    """Which node holds each sensor's data, and each one's calibration ("" none)."""
    if mode == "real":
        return {"a": "ingest[sensor=a]", "b": "ingest[sensor=b]"}
    return {"a": "render[skin=a]", "b": "render[skin=b]"}

def calib(mode):
    return {"a": "", "b": "cal[sensor=b]"} if mode == "real" else {"a": "cal[sensor=a]", "b": "cal[sensor=b]"}

def node_of(mode):
    return {"node": "ingest", "var": "sensor"} if mode == "real" else {"node": "render", "var": "skin"}

def members(mode, need):
    if need > 2:
        raise Missing(f"the set has 2 sensors, not {need}")
    return ["a", "b"]

def sets(table):
    return {name: list(members) for name, members in table.items()}
'''


@pytest.fixture()
def wired(tmp_path, monkeypatch):
    from pipeline.graph import Listing, Wiring
    (tmp_path / "wirer_mod.py").write_text(WIRER)
    monkeypatch.syspath_prepend(str(tmp_path))
    mode = {"mode": "data.mode"}
    g = Graph()
    g.node("render", "m:r", grid={"skin": ["a", "b"]})
    g.node("ingest", "m:i", grid={"sensor": ["a", "b"]})
    g.node("cal", "m:c", grid={"sensor": ["a", "b"]})
    g.node("fit", "m:f", inputs={"seq": "{where[{skin}]}", "calibration": "{calib[{skin}]}"},
           params={"lr": "lr", "where": Wiring("wirer_mod:where", mode), "calib": Wiring("wirer_mod:calib", mode)},
           grid={"skin": ["a", "b"]})
    g.node("study", "m:s", inputs={"seqs": "{src[node]}[{src[var]}=@members]", "fits": "fit[*]"},
           params={"src": Wiring("wirer_mod:node_of", mode),
                   "members": Listing("wirer_mod:members", {"mode": "data.mode", "need": "need"})})
    g.node("other", "m:o", inputs={"fit": "fit[skin=a]"})
    return g


def test_wiring_chooses_inputs_and_stays_out_of_params(wired):
    """A Wiring param picks the inputs ("{where[{skin}]}" indexes it by the instance's skin;
    "" leaves an input out); the function and the cache key see only the chosen inputs."""
    sim = wired.expand({"data": {"mode": "sim"}, "lr": 0.1, "need": 2})
    real = wired.expand({"data": {"mode": "real"}, "lr": 0.1, "need": 2})
    assert sim["fit[skin=b]"].inputs == {"seq": "render[skin=b]", "calibration": "cal[sensor=b]"}
    assert real["fit[skin=b]"].inputs == {"seq": "ingest[sensor=b]", "calibration": "cal[sensor=b]"}
    assert real["fit[skin=a]"].inputs == {"seq": "ingest[sensor=a]"}                 # no calibration
    assert sim["fit[skin=a]"].params == real["fit[skin=a]"].params == {"lr": 0.1}
    assert sim["fit[skin=a]"].param_keys == ["lr", "data.mode"]                     # dvc still sees the mode
    assert sim["study"].inputs["seqs"] == {"a": "render[skin=a]", "b": "render[skin=b]"}
    assert real["study"].inputs["seqs"] == {"a": "ingest[sensor=a]", "b": "ingest[sensor=b]"}
    assert real["study"].params == {"members": ["a", "b"]}
    assert wired.closure(real, ["fit[skin=a]"]) == ["ingest[sensor=a]", "fit[skin=a]"]


def test_a_mapping_param_selector_gathers_each_instances_own_members(wired):
    """'up[var=@arg.{g}]' reads the list a mapping param holds at the instance's value of g:
    each fine-tune of a set gathers its set's sensors only, so one set's bad sensor is no
    input of another's; an entry the mapping lacks is an error naming it."""
    from pipeline.graph import Wiring
    wired.node("tune", "m:t", inputs={"seqs": "{src[node]}[{src[var]}=@sets.{fit}]"},
               params={"src": Wiring("wirer_mod:node_of", {"mode": "data.mode"}),
                       "sets": Wiring("wirer_mod:sets", {"table": "table"})},
               grid={"fit": "fits"})
    base = {"data": {"mode": "real"}, "lr": 0.1, "need": 2, "fits": ["x", "y"]}
    inst = wired.expand({**base, "table": {"x": ["a"], "y": ["b", "a"]}})
    assert inst["tune[fit=x]"].inputs == {"seqs": {"a": "ingest[sensor=a]"}}
    assert inst["tune[fit=y]"].inputs == {"seqs": {"a": "ingest[sensor=a]", "b": "ingest[sensor=b]"}}
    assert inst["tune[fit=x]"].params == {} and "table" in inst["tune[fit=x]"].param_keys
    with pytest.raises(PipelineError, match=r"^node 'tune\[fit=y\]' input 'seqs': param sets has no entry 'y' "
                                            r"to select ingest's sensor$"):
        wired.expand({**base, "table": {"x": ["a"]}})


def test_a_listing_param_error_waits_for_a_run_that_needs_its_node(wired):
    """A Listing param's user error does not stop the plan: the rest expands and runs, the
    default targets leave the node (and what needs it) out, and naming it is the error."""
    inst = wired.expand({"data": {"mode": "real"}, "lr": 0.1, "need": 3})
    assert inst["study"].problem == "the set has 2 sensors, not 3" and inst["study"].inputs == {}
    unused = ["render[skin=a]", "render[skin=b]", "cal[sensor=a]"]      # the real data reads none of these
    assert wired.select(inst, None) == unused + ["fit[skin=b]", "other"]
    assert wired.closure(inst, ["other"]) == ["ingest[sensor=a]", "fit[skin=a]", "other"]
    with pytest.raises(PipelineError, match=r"^node study: the set has 2 sensors, not 3$"):
        wired.closure(inst, wired.select(inst, ["study"]))
    assert wired.select(wired.expand({"data": {"mode": "real"}, "lr": 0.1, "need": 2}), None) == unused + [
        "study", "other"]


def test_an_indexed_template_names_an_unknown_variable():
    g = Graph()
    g.node("up", "m:u", grid={"s": ["a"]})
    g.node("down", "m:d", inputs={"x": "{m[{nope}]}"}, params={"m": "m"}, grid={"s": ["a"]})
    with pytest.raises(PipelineError, match=r"node 'down\[s=a\]' input 'x': template '\{m\[\{nope\}\]\}' uses a "
                                            r"variable or key not in its grid \['s'\] or params"):
        g.expand({"m": {"a": "up[s=a]"}})
