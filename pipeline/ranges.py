"""Param ranges: the values each param may take, declared in one file beside the params.

`[tool.pipeline] ranges = "params.ranges.yaml"` names the file.  Each entry maps a dotted param
path (`*` matches any one key at its level: `sensors.*.spacing_mm`) to a rule:

  gt, ge, lt, le: n        a number's bounds (a list's or mapping's values: use `items`)
  one_of: [a, b, ...]      one of these values
  key_of: path | [paths]   a key of that params mapping (a name in a catalogue)
  len: n, min_len, max_len a list's length
  items: {rule}            every item of a list, or every value of a mapping
  whole: true              a whole number (an int, or a float such as 3.0)
  multiple_of: n           a whole multiple of n (image sides a network halves k times)
  nullable: true           null passes (the rest of the rule checks other values)

Checked on the merged params (base, profile, -p overrides) before anything runs, so a value
a node could not use fails in one line naming the key, the value, the rule and where the value
came from, not as the node's traceback minutes later.  The engine knows no key: the rules are
the project's.
"""
from __future__ import annotations

import math
from pathlib import Path
from typing import Any, Callable

from pipeline.errors import PipelineError

BOUNDS = {"gt": (">", lambda v, b: v > b), "ge": (">=", lambda v, b: v >= b),
          "lt": ("<", lambda v, b: v < b), "le": ("<=", lambda v, b: v <= b)}
RULE_KEYS = set(BOUNDS) | {"one_of", "key_of", "len", "min_len", "max_len", "items", "whole", "nullable",
                           "multiple_of"}


def load(path: Path, load_yaml: Callable) -> list[tuple[str, dict, str]]:
    """[(pattern, rule, 'file:line')] from the ranges file, its own mistakes one line each."""
    doc, lines = load_yaml(path)
    out = []
    for pattern, rule in doc.items():
        where = f"{path}:{lines.get(str(pattern), '?')}"
        _check_rule(str(pattern), rule, where)
        out.append((str(pattern), rule, where))
    return out


def _check_rule(pattern: str, rule: Any, where: str) -> None:
    if not isinstance(rule, dict) or not rule:
        raise PipelineError(f"ranges file {where}: the rule of '{pattern}' must be a mapping such as {{gt: 0}}")
    unknown = set(rule) - RULE_KEYS
    if unknown:
        raise PipelineError(f"ranges file {where}: '{pattern}' has unknown rule(s) {', '.join(sorted(map(str, unknown)))} "
                            f"(known: {', '.join(sorted(RULE_KEYS))})")
    for k in [*BOUNDS, "multiple_of"]:
        if k in rule and not _number(rule[k]):
            raise PipelineError(f"ranges file {where}: '{pattern}' {k} must be a number, got {rule[k]!r}")
    for k in ("len", "min_len", "max_len"):
        if k in rule and (not isinstance(rule[k], int) or isinstance(rule[k], bool) or rule[k] < 0):
            raise PipelineError(f"ranges file {where}: '{pattern}' {k} must be a whole number >= 0, got {rule[k]!r}")
    if "one_of" in rule and not isinstance(rule["one_of"], list):
        raise PipelineError(f"ranges file {where}: '{pattern}' one_of must be a list")
    if "items" in rule:
        _check_rule(f"{pattern} items", rule["items"], where)


def _number(v: Any) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool)


def matches(params: dict, pattern: str) -> list[tuple[str, Any]]:
    """(dotted key, value) of every param the pattern names."""
    found = [("", params)]
    for part in pattern.split("."):
        nxt = []
        for key, node in found:
            if not isinstance(node, dict):
                continue
            names = list(node) if part == "*" else [part] if part in node else []
            nxt += [(f"{key}.{n}" if key else str(n), node[n]) for n in names]
        found = nxt
    return found


def check(params: dict, rules: list[tuple[str, dict, str]], where_of: Callable[[str], str]) -> None:
    """Raise a one-line PipelineError for the first param outside its range."""
    for pattern, rule, rule_at in rules:
        hits = matches(params, pattern)
        if not hits:
            raise PipelineError(f"ranges file {rule_at}: '{pattern}' names no param")
        for key, value in hits:
            problem = _violation(value, rule, params, key)
            if problem:
                name, bad, why = problem
                raise PipelineError(f"param '{name}' = {_show(bad)} ({where_of(key)}) {why} "
                                    f"(range '{pattern}' in {rule_at})")


def _show(v: Any) -> str:
    text = repr(v)
    return text if len(text) <= 60 else text[:57] + "..."


def _violation(value: Any, rule: dict, params: dict, key: str) -> tuple[str, Any, str] | None:
    """(the offending key, its value, what it must be), or None when the value is in range."""
    if value is None:
        return None if rule.get("nullable") else (key, value, "must not be null")
    if "one_of" in rule and value not in rule["one_of"]:
        return key, value, f"must be one of {', '.join(map(str, rule['one_of']))}"
    if "key_of" in rule:
        paths = rule["key_of"] if isinstance(rule["key_of"], list) else [rule["key_of"]]
        names: list[str] = []
        for p in paths:
            got = matches(params, p)
            names += [str(k) for _, m in got if isinstance(m, dict) for k in m]
        if not isinstance(value, str) or value not in names:
            return key, value, f"must name an entry of {' or '.join(paths)}"
    bounds = [k for k in BOUNDS if k in rule]
    if bounds or rule.get("whole") or "multiple_of" in rule:
        # an int is finite however long (400 digits overflow a float: compare it exactly)
        if not _number(value) or (isinstance(value, float) and not math.isfinite(value)):
            return key, value, "must be a finite number"
        for k in bounds:
            sign, ok = BOUNDS[k]
            if not ok(value, rule[k]):
                return key, value, f"must be {sign} {rule[k]}"
        if rule.get("whole") and isinstance(value, float) and not value.is_integer():
            return key, value, "must be a whole number"
        if "multiple_of" in rule and value % rule["multiple_of"]:
            return key, value, f"must be a multiple of {rule['multiple_of']}"
    lengths = [k for k in ("len", "min_len", "max_len") if k in rule]
    if lengths:
        if not isinstance(value, list):
            return key, value, "must be a list"
        n = len(value)
        if "len" in rule and n != rule["len"]:
            return key, value, f"must have {rule['len']} items, has {n}"
        if "min_len" in rule and n < rule["min_len"]:
            return key, value, f"must have at least {rule['min_len']} items, has {n}"
        if "max_len" in rule and n > rule["max_len"]:
            return key, value, f"must have at most {rule['max_len']} items, has {n}"
    if "items" in rule:
        items = value.items() if isinstance(value, dict) else enumerate(value) if isinstance(value, list) else None
        if items is None:
            return key, value, "must be a list or a mapping"
        for i, item in items:
            sub = f"{key}.{i}" if isinstance(value, dict) else f"{key}[{i}]"
            problem = _violation(item, rule["items"], params, sub)
            if problem:
                return problem
    return None
