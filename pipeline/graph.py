"""Nodes, fan-out grids, instances and target selection.

A node is a pure function named by import path ("pkg.module:function"), its inputs
(other nodes' artifacts), the params keys it reads, and optionally a grid to fan out
over. An instance of a node with a grid is named `node[var=value,...]`.

Input references:
  "up"                     one instance of `up`: its only one, or the one whose grid
                           values equal this instance's values of the same variables
  "up[sensor={source}]"    a template filled from this instance's grid values
  "up[*]" / "up[a=1]"      gather: every matching instance, passed as a dict keyed by
                           the remaining grid values ("b=2" or just "2" for one variable)
  "up[a=@params.key]"      gather the instances whose `a` is in that params list (keyed
                           by `a` too), so a node needs only the instances it reads
  "up[a=@arg.{var}]"       the same with the list a node param (a mapping) holds at this
                           instance's value of var: each instance gathers its own members
  "{seq[{skin}]}"          a template indexing a node param by this instance's grid value; a
                           reference that formats to "" is no input (the function's default)

A grid entry's values come from params (a key, or keys joined by " + "), a literal list, or
a `Listing`: a light plan-time function named by import path that lists them from params
values and the world they name (the folders of a dataset), e.g. the sensors a dataset holds.
A `Wiring` param (a Listing) only chooses a node's inputs: templates and selectors read it, the
function and the cache key do not.  A Listing param that fails with a user error does not stop
the plan: its instance carries the error, raised when a run needs that instance.
"""
from __future__ import annotations

import copy
import difflib
import importlib
import re
import string
from dataclasses import dataclass, field
from typing import Any, Mapping

from pipeline import params as P
from pipeline.errors import PipelineError

_NAME = re.compile(r"^[A-Za-z_][A-Za-z0-9_]*$")
_REF = re.compile(r"^(?P<node>[A-Za-z_][A-Za-z0-9_]*)(\[(?P<sel>[^\]]*)\])?$")
_VAR = re.compile(r"\{([A-Za-z_][A-Za-z0-9_]*)\}")


@dataclass(frozen=True)
class Listing:
    """Grid values listed at plan time by `func` ("module:function", imported by path like a
    node's function), called with the values of `params` (argument -> dotted params key) and
    the constants `args` as keyword arguments; it returns the list.  As a node's param, its
    value (a list or a mapping) is the param's, and "@arg" selectors may read it.  It runs whenever the graph
    expands (every verb, `status` included), so it must be fast and import nothing heavy: list
    folders, not read data.  An exception whose class sets `user_error = True` is reported as
    one line (exit 2)."""
    func: str
    params: Mapping[str, str] = field(default_factory=dict)
    args: Mapping[str, Any] = field(default_factory=dict)

    def describe(self) -> str:
        keys = ", ".join(self.params.values())
        return f"{self.func}({keys})"


@dataclass(frozen=True)
class Wiring(Listing):
    """A node param that only chooses the node's inputs (e.g. which node holds a sensor's data
    under these params): resolved as a Listing param and read by input templates and "@"
    selectors, but neither passed to the function nor part of its params or cache key, which
    the chosen inputs' digests already determine."""


@dataclass(frozen=True)
class Node:
    name: str
    func: str
    inputs: dict[str, str] = field(default_factory=dict)
    params: dict[str, Any] = field(default_factory=dict)  # arg -> params key or Listing
    grid: dict[str, Any] = field(default_factory=dict)   # var -> params key(s), literal list or Listing
    version: str | None = None       # overrides the code fingerprint when set
    source: bool = False             # captured data: never re-run automatically
    on_demand: bool = False          # left out of the default targets: runs when named
    description: str = ""

    @property
    def grid_vars(self) -> list[str]:
        """Grid variable names (a zipped entry "a,b" names two)."""
        return [v.strip() for entry in self.grid for v in entry.split(",")]


@dataclass
class Instance:
    node: Node
    bindings: tuple[tuple[str, Any], ...]
    params: dict[str, Any]                       # resolved: arg -> value
    inputs: dict[str, str | dict[str, str]] = field(default_factory=dict)  # arg -> instance name(s)
    param_keys: list[str] = field(default_factory=list)  # resolved dotted keys (for dvc)
    problem: str | None = None    # a Listing param's user error: raised when a run needs this instance

    @property
    def name(self) -> str:
        return instance_name(self.node.name, self.bindings)

    def upstream(self) -> list[str]:
        out: list[str] = []
        for v in self.inputs.values():
            out += list(v.values()) if isinstance(v, dict) else [v]
        return out


def _fmt(value: Any) -> str:
    return str(value).lower() if isinstance(value, bool) else str(value)


def instance_name(node: str, bindings) -> str:
    if not bindings:
        return node
    return f"{node}[{','.join(f'{k}={_fmt(v)}' for k, v in bindings)}]"


def parse_selector(text: str) -> tuple[str, dict[str, str] | None]:
    """'render[sensor=a, x=1]' -> ('render', {'sensor': 'a', 'x': '1'}); '[*]' -> {}; '[]' is refused."""
    m = _REF.match(text.strip().replace(" ", ""))
    if not m:
        raise PipelineError(f"malformed target or reference {text!r}: expected NODE or NODE[var=value,...]")
    sel = m.group("sel")
    if sel is None:
        return m.group("node"), None
    if sel == "*":
        return m.group("node"), {}
    if not sel:     # "render[]" is a slip, not "every instance" (that is "render[*]")
        raise PipelineError(f"malformed target or reference {text!r}: empty brackets; "
                            f"use {m.group('node')} or {m.group('node')}[*] for every instance")
    out = {}
    for part in sel.split(","):
        k, eq, v = part.partition("=")
        if not eq or not _NAME.match(k) or not v:
            raise PipelineError(f"malformed selector {part!r} in {text!r}: expected var=value")
        out[k] = v
    return m.group("node"), out


class Graph:
    """The DAG declaration: `graph.node(...)` calls in one module."""

    def __init__(self, default_targets: list[str] | None = None):
        self.nodes: dict[str, Node] = {}
        self.default_targets = default_targets

    def node(self, name: str, func: str, *, inputs: dict[str, str] | None = None,
             params: dict[str, str] | None = None, grid: dict[str, Any] | None = None,
             version: str | None = None, source: bool = False, on_demand: bool = False,
             description: str = "") -> Node:
        if not _NAME.match(name):
            raise PipelineError(f"invalid node name {name!r}")
        if name in self.nodes:
            raise PipelineError(f"node '{name}' declared twice")
        if ":" not in func:
            raise PipelineError(f"node '{name}': func must be 'module:function', got {func!r}")
        n = Node(name, func, dict(inputs or {}), dict(params or {}), dict(grid or {}),
                 version, source, on_demand, description)
        grid_vars = n.grid_vars
        for entry, spec in n.grid.items():
            if isinstance(spec, Listing) and ":" not in spec.func:
                raise PipelineError(f"node '{name}' grid '{entry}': Listing func must be "
                                    f"'module:function', got {spec.func!r}")
        for arg in [*n.inputs, *n.params, *grid_vars]:
            if not _NAME.match(arg):
                raise PipelineError(f"node '{name}': invalid argument name {arg!r}")
        clash = set(n.inputs) & set(n.params) | (set(n.inputs) | set(n.params)) & set(grid_vars)
        if clash:
            raise PipelineError(f"node '{name}': argument(s) {sorted(clash)} declared twice")
        self.nodes[name] = n
        return n

    # -- expansion -------------------------------------------------------------------

    def expand(self, params: dict) -> dict[str, Instance]:
        """All instances in topological order, inputs resolved to instance names.

        Nodes expand depth first from their inputs; an input whose node name is a template
        ("{spec[source]}[skin={skin}]") is resolved per instance, so dependencies can depend
        on params."""
        by_node: dict[str, list[Instance]] = {}
        out: dict[str, Instance] = {}
        state: dict[str, int] = {}

        def visit(name: str, stack: list[str]) -> None:
            if state.get(name) == 2:
                return
            if state.get(name) == 1:
                raise PipelineError(f"cycle in graph: {' -> '.join(stack + [name])}")
            state[name] = 1
            node = self.nodes[name]
            for arg, ref in node.inputs.items():  # static names first, with a clear error
                up = ref.partition("[")[0].strip()
                if "{" not in up:
                    if up not in self.nodes:
                        raise PipelineError(f"node '{name}' input '{arg}' names unknown node '{up}'")
                    visit(up, stack + [name])
            points = self._grid_points(node, params)
            listed = _listed_params(node, params) if points else {}
            made = [self._instance(node, b, params, by_node, lambda up: visit(up, stack + [name]), listed)
                    for b in points]
            by_node[name] = made
            out.update((i.name, i) for i in made)
            state[name] = 2

        for name in self.nodes:
            visit(name, [])
        return out

    def _grid_points(self, node: Node, params: dict) -> list[tuple[tuple[str, Any], ...]]:
        """Grid points as ((var, value), ...) tuples, the product over the grid's entries.

        An entry is `var: spec` or, zipped, `"a,b": spec` whose values are [a, b] lists (e.g.
        source/target pairs).  spec is a literal list, a params key (a dict gives its keys),
        params keys joined by " + " (their lists concatenated, repeats dropped), or a Listing
        (the list its function returns).  An empty list gives the node no instances: a '[*]'
        gather of it is then empty, any other reference to it an error."""
        points: list[tuple[tuple[str, Any], ...]] = [()]
        for entry, spec in node.grid.items():
            names = [v.strip() for v in entry.split(",")]
            if isinstance(spec, Listing):
                values = _listed(node.name, entry, spec, params)
            elif isinstance(spec, str):
                values: list = []
                for key in (k.strip() for k in spec.split("+")):
                    got = P.get(params, key)
                    got = list(got) if isinstance(got, dict) else got
                    if not isinstance(got, list):
                        raise PipelineError(f"node '{node.name}' grid '{entry}' ({key}) must be a list")
                    values += [v for v in got if v not in values]
            else:
                values = spec
            if not isinstance(values, list):
                raise PipelineError(f"node '{node.name}' grid '{entry}' ({spec}) must be a list")
            rows = []
            for v in values:
                row = v if len(names) > 1 else [v]
                if not isinstance(row, list) or len(row) != len(names):
                    raise PipelineError(f"node '{node.name}' grid '{entry}': invalid value {v!r} "
                                        f"(expected a list of {len(names)})")
                for x in row:
                    if not isinstance(x, (str, int, float, bool)) or not re.match(r"^[^\[\],=\s{}]+$", _fmt(x)):
                        raise PipelineError(f"node '{node.name}' grid '{entry}': invalid value {x!r}")
                rows.append(tuple(zip(names, row)))
            points = [p + r for p in points for r in rows]
        return points

    def _instance(self, node: Node, bindings, params, by_node, need, listed) -> Instance:
        env = {k: _fmt(v) for k, v in bindings}
        resolved, keys, problem = {}, [], None
        for arg, key in node.params.items():
            if isinstance(key, Listing):
                keys += [k for k in key.params.values() if k not in keys]
                if isinstance(listed[arg], _UserError):   # this instance's problem, not the plan's
                    problem = problem or str(listed[arg])
                else:   # a copy each: a function that changes its param changes no other instance's
                    resolved[arg] = copy.deepcopy(listed[arg])
                continue
            dotted = key.format(**env)
            try:
                resolved[arg] = P.get(params, dotted)
            except PipelineError:
                if dotted == key:
                    raise
                used = {k: v for k, v in env.items() if "{" + k + "}" in key}
                grids = [spec for spec in node.grid.values() if isinstance(spec, str)]
                raise PipelineError(
                    f"node '{node.name}' has no param '{dotted}' for "
                    f"{', '.join(f'{k}={v}' for k, v in used.items())}: is that value in "
                    f"{' / '.join(grids) or 'its grid'} a typo?") from None
            keys.append(dotted)
        keys += [k.strip() for spec in node.grid.values() if isinstance(spec, str) for k in spec.split("+")]
        listed = [k for spec in node.grid.values() if isinstance(spec, Listing) for k in spec.params.values()]
        keys += [k for k in dict.fromkeys(listed) if k not in keys]
        passed = {k: v for k, v in resolved.items() if not isinstance(node.params[k], Wiring)}
        inst = Instance(node, tuple(bindings), passed, param_keys=keys, problem=problem)
        for arg, ref in node.inputs.items():
            if problem is not None:
                break
            try:  # templates use grid values and the instance's params: "{spec[source]}[skin={skin}]"
                text = _Template(env).format(ref, **resolved, **env)
            except (KeyError, IndexError, TypeError, AttributeError, ValueError):
                raise PipelineError(f"node '{inst.name}' input '{arg}': template {ref!r} uses a "
                                    f"variable or key not in its grid {list(env)} or params") from None
            if not text.strip():     # a wiring value left this input out
                continue
            up_name, sel = parse_selector(text)
            if up_name not in self.nodes:
                raise PipelineError(f"node '{inst.name}' input '{arg}': unknown node '{up_name}'")
            need(up_name)
            candidates = by_node[up_name]
            up_vars = self.nodes[up_name].grid_vars
            if sel is None:  # match on shared variable names
                shared = {k: v for k, v in env.items() if k in up_vars}
                match = [c for c in candidates if all(_fmt(dict(c.bindings)[k]) == v for k, v in shared.items())]
                if len(match) != 1:
                    raise PipelineError(
                        f"node '{inst.name}' input '{arg}': '{ref}' matches {len(match)} instances; "
                        f"use '{up_name}[var=...]' or '{up_name}[*]'")
                inst.inputs[arg] = match[0].name
            else:
                unknown = set(sel) - set(up_vars)
                if unknown:
                    raise PipelineError(f"node '{node.name}' input '{arg}': '{up_name}' has no grid "
                                        f"variable {sorted(unknown)}")
                within = {}             # var -> the values a "var=@params.key" selector allows
                for k, v in sel.items():
                    if v.startswith("@"):   # a node param of this instance (or a key of it), else a params key
                        head, _, within_key = v[1:].partition(".")
                        if head in resolved:
                            got = resolved[head]
                            if within_key:
                                if not isinstance(got, Mapping) or within_key not in got:
                                    raise PipelineError(f"node '{inst.name}' input '{arg}': param {head} "
                                                        f"has no entry {within_key!r} to select {up_name}'s {k}")
                                got = got[within_key]
                        else:
                            got = P.get(params, v[1:])
                        if not isinstance(got, list):
                            raise PipelineError(f"node '{node.name}' input '{arg}': {v[1:]} must be a "
                                                f"list to select {up_name}'s {k}, got {type(got).__name__}")
                        within[k] = {_fmt(x) for x in got}
                        if head not in resolved:
                            inst.param_keys.append(v[1:])

                def chosen(c):
                    b = dict(c.bindings)
                    return all(_fmt(b[k]) in within[k] if k in within else _fmt(b[k]) == v
                               for k, v in sel.items())
                match = [c for c in candidates if chosen(c)]
                if not match and sel and not within:   # "[*]" (or an empty list) may gather nothing
                    raise PipelineError(f"node '{inst.name}' input '{arg}': no instance matches '{ref}'")
                if set(sel) == set(up_vars) and not within:
                    inst.inputs[arg] = match[0].name
                else:
                    rest = [v for v in up_vars if v not in sel or v in within]
                    gathered = {}
                    for c in match:
                        b = dict(c.bindings)
                        label = _fmt(b[rest[0]]) if len(rest) == 1 else \
                            ",".join(f"{v}={_fmt(b[v])}" for v in rest)
                        gathered[label] = c.name
                    inst.inputs[arg] = gathered
        return inst

    # -- targets ---------------------------------------------------------------------

    def select(self, instances: dict[str, Instance], targets: list[str] | None) -> list[str]:
        """Instance names named by targets (node names, instances or partial selectors)."""
        targets = list(targets or self.default_targets or [])
        if not targets:  # default: every sink but source and on-demand nodes (they run when named),
            blocked: set[str] = set()   # of what these params can run (see Instance.problem)
            for n, i in instances.items():
                if i.problem is not None or any(u in blocked for u in i.upstream()):
                    blocked.add(n)
            used = {u for n, i in instances.items() if n not in blocked for u in i.upstream()}
            return [n for n, i in instances.items()
                    if n not in used and n not in blocked and not i.node.source and not i.node.on_demand]
        chosen: list[str] = []
        for t in targets:
            node, sel = parse_selector(t)
            if node not in self.nodes:
                close = difflib.get_close_matches(node, list(self.nodes), n=1)
                hint = f"; did you mean '{close[0]}'?" if close else ""
                raise PipelineError(f"unknown target '{t}'{hint}")
            grid = self.nodes[node].grid_vars
            if sel:
                bad = set(sel) - set(grid)
                if bad:
                    raise PipelineError(f"unknown target '{t}': node '{node}' has no grid variable "
                                        f"{sorted(bad)} (its grid: {list(grid) or 'none'})")
            match = [i.name for i in instances.values() if i.node.name == node and
                     all(_fmt(dict(i.bindings)[k]) == v for k, v in (sel or {}).items())]
            if not match and not any(i.node.name == node for i in instances.values()):
                grids = [spec.describe() if isinstance(spec, Listing) else spec
                         for spec in self.nodes[node].grid.values() if isinstance(spec, (str, Listing))]
                raise PipelineError(f"unknown target '{t}': '{node}' has no instance for these params "
                                    f"(its grid {' / '.join(grids)} is empty)")
            if not match:
                raise PipelineError(f"unknown target '{t}': no instance of '{node}' has those values")
            chosen += [m for m in match if m not in chosen]
        return chosen

    def closure(self, instances: dict[str, Instance], names: list[str]) -> list[str]:
        """The named instances and all their ancestors, in topological order; an error if one
        of them could not be planned (Instance.problem)."""
        need: set[str] = set()
        stack = list(names)
        while stack:
            n = stack.pop()
            if n not in need:
                if instances[n].problem is not None:
                    raise PipelineError(f"node {n}: {instances[n].problem}")
                need.add(n)
                stack += instances[n].upstream()
        return [n for n in instances if n in need]


class _UserError(PipelineError):
    """A Listing's own one-line error (its exception class sets user_error)."""


class _Template(string.Formatter):
    """str.format whose indices may name grid variables in braces: "{seq[{skin}]}" reads the
    param seq at this instance's value of skin."""

    def __init__(self, env: Mapping[str, str]):
        super().__init__()
        self.env = env

    def get_field(self, field_name, args, kwargs):
        return super().get_field(_VAR.sub(lambda m: self.env[m.group(1)], field_name), args, kwargs)


def _listed_params(node: Node, params: dict) -> dict[str, Any]:
    """A node's Listing params' values (the same for all its instances), or their user errors."""
    out: dict[str, Any] = {}
    for arg, spec in node.params.items():
        if isinstance(spec, Listing):
            try:
                out[arg] = _listed(node.name, arg, spec, params, kinds=(list, dict))
            except _UserError as exc:
                out[arg] = exc
    return out


def _listed(node: str, entry: str, spec: Listing, params: dict, kinds=(list,)):
    """The values a Listing (grid entry or node param) returns for these params."""
    kwargs = {**spec.args, **{arg: P.get(params, key) for arg, key in spec.params.items()}}
    module, _, name = spec.func.partition(":")
    try:
        func = getattr(importlib.import_module(module), name)
    except (ImportError, AttributeError) as exc:
        raise PipelineError(f"node '{node}' grid '{entry}': cannot import '{spec.func}': {exc}") from None
    try:
        values = func(**kwargs)
    except PipelineError:
        raise
    except Exception as exc:  # noqa: BLE001 - a listing's failure is the plan's, in one line
        if getattr(exc, "user_error", False) is True:
            raise _UserError(str(exc)) from None
        raise PipelineError(f"node '{node}' grid '{entry}': {spec.func} failed: "
                            f"{type(exc).__name__}: {exc}") from None
    if not isinstance(values, kinds):
        raise PipelineError(f"node '{node}' grid '{entry}': {spec.func} returned "
                            f"{type(values).__name__}, not a {' or '.join(k.__name__ for k in kinds)}")
    return values
