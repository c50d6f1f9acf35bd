"""Params: the base file is the schema; profiles and -p overrides may only change values.

A value may change to another of the same type (an int is accepted where a float is
expected); lists keep their element type; unknown keys are rejected with the file and
line that named them.
"""
from __future__ import annotations

import copy
import difflib
import math
import re
from pathlib import Path
from typing import Any

import yaml

from pipeline.errors import PipelineError
from pipeline.extends import resolve as resolve_extends

_KEY = re.compile(r"^[A-Za-z_][A-Za-z0-9_\-]*(\.[A-Za-z0-9_\-]+)*$")


class Loader(getattr(yaml, "CSafeLoader", yaml.SafeLoader)):   # libyaml's parser when built with it
    """YAML 1.1 reads 1.45e5 as a string; scientists write moduli that way."""


Loader.add_implicit_resolver(
    "tag:yaml.org,2002:float",
    re.compile(r"^[-+]?(?:[0-9][0-9_]*\.[0-9_]*|\.[0-9_]+|[0-9][0-9_]*)(?:[eE][-+]?[0-9]+)?$"
               r"|^[-+]?\.(?:inf|Inf|INF)$|^\.(?:nan|NaN|NAN)$"),
    list("-+0123456789."))


MAX_NODES = 200_000   # values a params file may expand to: aliases beyond that are a bomb


def safe_load(text: str, what: str = "YAML"):
    """The YAML's data, refused when its aliases expand to more than MAX_NODES values (a
    "billion laughs" file would otherwise take forever and all memory in what reads it)."""
    loader = Loader(text)
    try:
        node = loader.get_single_node()
        if node is not None:
            _bounded(node, what)
            return loader.construct_document(node)
        return None
    finally:
        loader.dispose()


def _bounded(root, what: str) -> None:
    """Count the values the node graph expands to, each shared node's size computed once,
    so that counting stays linear in the file however far its aliases expand."""
    sizes: dict[int, int | None] = {}      # None: being counted (a node inside itself counts 1)
    stack: list = [(root, None)]
    while stack:
        node, kids = stack.pop()
        if kids is None:
            if id(node) in sizes:
                continue
            kids = ([c for kv in node.value for c in kv] if isinstance(node, yaml.MappingNode)
                    else node.value if isinstance(node, yaml.SequenceNode) else ())
            sizes[id(node)] = None
            stack.append((node, kids))
            stack += [(c, None) for c in kids
                      if not isinstance(c, yaml.ScalarNode) and id(c) not in sizes]
            continue
        sizes[id(node)] = total = 1 + sum(sizes.get(id(c)) or 1 for c in kids)
        if total > MAX_NODES:
            raise PipelineError(f"{what}: its aliases expand to more than {MAX_NODES} values "
                                "(an alias bomb?); write the values out, or use fewer aliases")


def _load_yaml(path: Path) -> tuple[Any, dict[str, int]]:
    """Parse YAML; return data and {dotted key: line number} for error messages."""
    try:
        text = path.read_text()
    except OSError as exc:
        raise PipelineError(f"cannot read params file {path}: {exc.strerror}") from None
    except UnicodeDecodeError as exc:
        raise PipelineError(f"params file {path} is not UTF-8 text (byte {exc.start})") from None
    loader = Loader(text)
    try:
        node = loader.get_single_node()
        if node is not None:
            _bounded(node, f"params file {path}")
    except yaml.YAMLError as exc:
        loader.dispose()
        raise _malformed(exc, path) from None
    lines: dict[str, int] = {}

    def walk(n, prefix):
        if isinstance(n, yaml.MappingNode):
            for k, v in n.value:
                key = f"{prefix}.{k.value}" if prefix else str(k.value)
                if key in lines:
                    raise PipelineError(f"duplicate param '{key}' in {path}:{k.start_mark.line + 1} "
                                        f"(first at line {lines[key]})")
                lines[key] = k.start_mark.line + 1
                walk(v, key)

    try:
        walk(node, "")    # before constructing: merge keys ("<<") are flattened in place then
        data = loader.construct_document(node) if node is not None else None
    except RecursionError:
        raise PipelineError(f"params file {path}: a YAML alias contains itself (recursive anchor)") from None
    except yaml.YAMLError as exc:
        raise _malformed(exc, path) from None
    except ValueError as exc:     # an integer past Python's digit limit for int()
        raise PipelineError(f"params file {path}: value out of range: an integer too long to read "
                            f"({exc.args[0].split(':')[0]})") from None
    finally:
        loader.dispose()
    if data is None:
        data = {}
    if not isinstance(data, dict):
        raise PipelineError(f"params file {path} must hold a mapping at the top level")
    return data, lines


def _malformed(exc: yaml.YAMLError, path: Path) -> PipelineError:
    mark = getattr(exc, "problem_mark", None)
    where = f"{path}:{mark.line + 1}" if mark else str(path)
    problem = getattr(exc, "problem", None) or str(exc).splitlines()[0]
    return PipelineError(f"malformed YAML in {where}: {problem}")


def _plain_yaml(v: Any) -> bool:
    if v is None or isinstance(v, (bool, int, float, str)):
        return True
    if isinstance(v, list):
        return all(_plain_yaml(x) for x in v)
    if isinstance(v, dict):
        return all(isinstance(k, str) and _plain_yaml(x) for k, x in v.items())
    return False


def _type_name(v: Any) -> str:
    return {bool: "bool", int: "int", float: "float", str: "str", list: "list",
            dict: "mapping", type(None): "null"}.get(type(v), type(v).__name__)


def _check_value(key: str, default: Any, value: Any, where: str) -> Any:
    """Return value coerced to the default's type, or raise naming key and place."""
    if default is None:  # untyped: any plain YAML value that hashes the same everywhere
        if not _plain_yaml(value):
            raise PipelineError(f"param '{key}' ({where}) must be a number, string, bool, list "
                                f"or mapping, got {type(value).__name__} {value!r}")
        return value
    if isinstance(default, bool) or isinstance(value, bool):
        ok = isinstance(default, bool) and isinstance(value, bool)
    elif isinstance(default, float):
        ok = isinstance(value, (int, float))
        if ok:
            try:
                value = float(value)
            except OverflowError:
                raise PipelineError(f"param '{key}' ({where}) must be a finite number, "
                                    f"got an integer of {len(str(value))} digits") from None
        if ok and not math.isfinite(value) and math.isfinite(default):
            raise PipelineError(f"param '{key}' ({where}) must be a finite number, got {value!r}")
    elif isinstance(default, int):
        ok = isinstance(value, int)
    elif isinstance(default, str):
        ok = isinstance(value, str)
    elif isinstance(default, list):
        ok = isinstance(value, list)
        if ok and default:
            proto = default[0]
            value = [_check_value(f"{key}[{i}]", proto, v, where) for i, v in enumerate(value)]
    elif isinstance(default, dict):
        ok = isinstance(value, dict)
    else:
        ok = type(value) is type(default)
    if not ok:
        raise PipelineError(f"param '{key}' ({where}) must be {_type_name(default)}, "
                            f"got {_type_name(value)} {value!r}")
    return value


def _unknown(key: str, schema: dict, where: str) -> PipelineError:
    parent, _, leaf = key.rpartition(".")
    try:
        holder = _lookup(schema, parent)
    except (KeyError, TypeError):
        holder = None
    options = list(holder) if isinstance(holder, dict) else []
    close = difflib.get_close_matches(leaf, [str(o) for o in options], n=1)
    hint = f"; did you mean '{(parent + '.') if parent else ''}{close[0]}'?" if close else ""
    return PipelineError(f"unknown param '{key}' ({where}){hint}")


def _lookup(tree: dict, dotted: str) -> Any:
    cur: Any = tree
    for part in dotted.split(".") if dotted else []:
        cur = cur[part]
    return cur


_MISSING = object()


def _inherited(root: dict, key: str) -> Any:
    """The value `key` has once `extends` is resolved (an entry's key it inherits), or _MISSING."""
    try:
        return _lookup(resolve_extends(root), key)
    except (KeyError, TypeError, PipelineError):
        return _MISSING


def _merge(schema: dict, base: dict, overlay: dict, prefix: str, where_of, root: dict | None = None,
           origins: dict | None = None) -> None:
    """Overlay values onto base, each checked against the type it has there; a key an entry
    inherits through `extends` may be set on the entry itself.  `origins` records where each
    value came from."""
    for k, v in overlay.items():
        key = f"{prefix}.{k}" if prefix else str(k)
        where = where_of(key)
        if not isinstance(base, dict):
            raise _unknown(key, schema, where)
        if k not in base:
            inherited = _MISSING if root is None else _inherited(root, key)
            if inherited is _MISSING:
                raise _unknown(key, schema, where)
            if isinstance(inherited, dict) and isinstance(v, dict):
                base[k] = {}
                _merge(schema, base[k], v, key, where_of, root, origins)
                continue
            base[k] = _check_value(key, inherited, v, where)
        elif isinstance(base[k], dict) and isinstance(v, dict):
            _merge(schema, base[k], v, key, where_of, root, origins)
            continue
        else:
            base[k] = _check_value(key, base[k], v, where)
        if origins is not None:
            origins[key] = where


def get(params: dict, dotted: str) -> Any:
    """The value at a dotted key; PipelineError if absent."""
    try:
        return _lookup(params, dotted)
    except (KeyError, TypeError):
        raise PipelineError(f"unknown param '{dotted}'") from None


def shown(text: str, limit: int = 80) -> str:
    """A user's text as an error line quotes it: cut to `limit` characters, so that a
    400-digit value still gives one readable line."""
    return text if len(text) <= limit else f"{text[:limit - 3]}..."


def parse_override(text: str) -> tuple[str, Any]:
    key, sep, raw = text.partition("=")
    key = key.strip()
    if not sep or not _KEY.match(key):
        raise PipelineError(f"malformed override {shown(text)!r}: expected KEY=VALUE with a dotted KEY")
    try:
        value = safe_load(raw, f"override {shown(text)!r}") if raw.strip() else ""
    except yaml.YAMLError:
        raise PipelineError(f"malformed value in override {shown(text)!r}: not valid YAML") from None
    except ValueError as e:     # an integer past Python's digit limit for int()
        raise PipelineError(f"value out of range in override {shown(text)!r}: "
                            f"an integer too long to read ({e.args[0].split(':')[0]})") from None
    return key, value


def load(base_file: Path, profile: str | None = None, overrides: list[str] = (),
         profiles_dir: Path | None = None, ranges_file: Path | None = None) -> dict:
    """params.yaml, then params/<profile>.yaml, then -p KEY=VALUE overrides, all validated:
    types against params.yaml; then every `extends` resolved (pipeline.extends); then values
    against the ranges file when there is one."""
    schema, base_lines = _load_yaml(base_file)
    params = copy.deepcopy(schema)
    origins: dict[str, str] = {}    # dotted key -> the profile line or -p that set it
    if profile is not None and not profile.strip():
        raise PipelineError("--profile is empty: name a profile (default, or a file of params/)")
    if profile and profile != "default":
        pdir = profiles_dir or base_file.parent / "params"
        pfile = pdir / f"{profile}.yaml"
        if not pfile.is_file():
            known = sorted(p.stem for p in pdir.glob("*.yaml")) if pdir.is_dir() else []
            raise PipelineError(f"unknown profile '{profile}' (known: {', '.join(['default'] + known)})")
        overlay, lines = _load_yaml(pfile)
        _merge(schema, params, overlay, "", lambda k: f"{pfile}:{lines.get(k, '?')}", params, origins)
    for text in overrides:
        key, value = parse_override(text)
        parent, _, leaf = key.rpartition(".")
        try:
            holder = _lookup(params, parent)
        except (KeyError, TypeError):
            holder = None
        if not isinstance(holder, dict):
            raise _unknown(key, schema, f"-p {shown(text)}")
        _merge(schema, holder, {leaf: value}, parent, lambda k: f"-p {shown(text)}", params, origins)
    params = resolve_extends(params)
    if ranges_file is not None:
        from pipeline import ranges

        def where_of(key: str) -> str:
            """The nearest setting of the key or of a mapping holding it: a value inherited
            through `extends` has no line of its own."""
            k = key
            while k:
                if k in origins:
                    return origins[k]
                if k in base_lines:
                    return f"{base_file}:{base_lines[k]}"
                k = k.rpartition(".")[0]
            return str(base_file)
        ranges.check(params, ranges.load(ranges_file, _load_yaml), where_of)
    return params
