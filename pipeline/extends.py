"""`extends`: a params entry that is another entry of the same mapping, changed.

An entry (a mapping inside a mapping) with the key `extends: NAME` is, once the params are
merged (base file, profile, -p overrides), the sibling entry NAME deep-merged with its own keys
(its own win; nested mappings merge key by key).  Chains resolve in order; `extends` itself
is dropped.  So a profile that changes a base entry changes every entry that extends it.
"""
from __future__ import annotations

import copy
from typing import Any

from pipeline.errors import PipelineError

KEY = "extends"


def _merged(base: dict, own: dict) -> dict:
    out = copy.deepcopy(base)
    for k, v in own.items():
        if isinstance(v, dict) and isinstance(out.get(k), dict):
            out[k] = _merged(out[k], v)
        else:
            out[k] = copy.deepcopy(v)
    return out


def resolve(tree: Any, prefix: str = "") -> Any:
    """`tree` with every `extends` resolved (a new tree; the input is not changed)."""
    if not isinstance(tree, dict):
        return tree
    done: dict[str, Any] = {}

    def entry(name: str, chain: list[str]):
        if name in done:
            return done[name]
        value = tree[name]
        if isinstance(value, dict) and KEY in value:
            parent = value[KEY]
            where = f"{prefix}{name}.{KEY}"
            if not isinstance(parent, str) or parent not in tree:
                known = ", ".join(k for k in tree if k != name)
                raise PipelineError(f"param '{where}' names {parent!r}, not an entry beside it ({known})")
            if parent in chain:
                raise PipelineError(f"param '{where}': entries extend each other in a loop "
                                    f"({' -> '.join(chain + [name, parent])})")
            base = entry(parent, chain + [name])
            if not isinstance(base, dict):
                raise PipelineError(f"param '{where}' names {parent!r}, which is not a mapping")
            value = _merged(base, {k: v for k, v in value.items() if k != KEY})
        done[name] = resolve(value, f"{prefix}{name}.")
        return done[name]

    return {name: entry(name, []) for name in tree}
