"""Metrics gathered from the store, and comparison with a committed baseline.

A baseline file (YAML or JSON) holds `metrics: {name: value}`, optionally `spread: {name:
sd}` with `k: K` (each metric's standard deviation measured over runs that differ only in
their seeds and CPU kernels, scripts/ci_baseline.py) and `tolerances: {glob: {abs: a, rel:
r}}` (first matching glob wins; default: abs 0, rel 0).  A metric regresses when it is worse
than the baseline by more than max(K * sd, abs, rel * |baseline|), in the metric's direction
(higher is better for r2, iou, success; lower for the rest), or when it is missing.
"""
from __future__ import annotations

import fnmatch
import math
from pathlib import Path

import yaml

from pipeline.errors import PipelineError

HIGHER_IS_BETTER = ("r2", "iou", "success", "accuracy", "speedup")


def higher_is_better(name: str) -> bool:
    """r2, iou, success...: higher is better; a spread (`<metric>_sd`) is better lower, as
    every other metric."""
    leaf = name.rsplit("/", 1)[-1]
    if leaf.endswith("_sd"):
        return False
    return any(leaf == h or leaf.startswith(h + "_") for h in HIGHER_IS_BETTER)


def collect(planned) -> dict[str, float]:
    out: dict[str, float] = {}
    for p in planned:
        for k, v in ((p.record or {}).get("metrics") or {}).items():
            if k in out and out[k] != v:
                raise PipelineError(f"metric '{k}' reported by two artifacts with different values")
            out[k] = v
    return dict(sorted(out.items()))


def load_baseline(path: Path) -> dict:
    try:
        doc = yaml.safe_load(Path(path).read_text())
    except OSError as exc:
        raise PipelineError(f"cannot read baseline {path}: {exc.strerror}") from None
    except UnicodeDecodeError as exc:
        raise PipelineError(f"baseline {path} is not UTF-8 text (byte {exc.start})") from None
    except yaml.YAMLError as exc:
        raise PipelineError(f"malformed baseline {path}: {str(exc).splitlines()[0]}") from None
    if not isinstance(doc, dict) or not isinstance(doc.get("metrics"), dict):
        raise PipelineError(f"baseline {path} must have a 'metrics' mapping")
    tol = doc.get("tolerances") or {}
    if not isinstance(tol, dict) or not all(isinstance(v, dict) for v in tol.values()):
        raise PipelineError(f"baseline {path}: 'tolerances' must map globs to {{abs, rel}}")
    for name, value in doc["metrics"].items():
        if not _number(value):
            raise PipelineError(f"baseline {path}: metric '{name}' must be a number, got {value!r}")
    for glob, t in tol.items():
        for k, v in t.items():
            if k not in ("abs", "rel") or not _number(v) or v < 0:
                raise PipelineError(f"baseline {path}: tolerance '{glob}' {k}={v!r}: "
                                    "expected abs or rel, a number >= 0")
    spread = doc.get("spread") or {}
    if not isinstance(spread, dict) or not all(_number(v) and v >= 0 for v in spread.values()):
        raise PipelineError(f"baseline {path}: 'spread' must map metrics to numbers >= 0")
    k = doc.get("k", 0)
    if not _number(k) or k < 0:
        raise PipelineError(f"baseline {path}: 'k' must be a number >= 0, got {k!r}")
    return {"metrics": doc["metrics"], "tolerances": tol, "spread": spread, "k": k}


def _number(v) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool)


def tolerance(name: str, tolerances: dict) -> float:
    for pattern, t in tolerances.items():
        if fnmatch.fnmatchcase(name, pattern):
            return t
    return {}


def compare(current: dict[str, float], baseline: dict) -> list[dict]:
    rows = []
    for name, base in sorted(baseline["metrics"].items()):
        t = tolerance(name, baseline["tolerances"])
        noise = float(baseline.get("k", 0)) * float((baseline.get("spread") or {}).get(name, 0.0))
        allowed = max(noise, float(t.get("abs", 0.0)), float(t.get("rel", 0.0)) * abs(float(base)))
        cur = current.get(name)
        if cur is None or (isinstance(cur, float) and math.isnan(cur)):
            rows.append({"metric": name, "baseline": base, "current": None, "allowed": allowed,
                         "regression": True, "why": "missing"})
            continue
        worse = (base - cur) if higher_is_better(name) else (cur - base)
        rows.append({"metric": name, "baseline": base, "current": cur, "allowed": allowed,
                     "regression": worse > allowed + 1e-12, "why": f"worse by {worse:.4g}" if worse > 0 else ""})
    return rows


def merged_worse(baseline: dict[str, float], current: dict[str, float]) -> dict[str, float]:
    """Per metric the worse of the baseline's value and the current one (in the metric's
    direction); metrics in only one of the two are kept as they are.  A baseline merged this
    way on every machine type CI may run on holds on each of them: torch's CPU kernels differ
    across CPU types, and a short training amplifies the difference."""
    out = dict(baseline)
    for name, cur in current.items():
        base = out.get(name)
        if not _number(base) or not _number(cur) or math.isnan(cur):
            out.setdefault(name, cur)
            continue
        out[name] = min(base, cur) if higher_is_better(name) else max(base, cur)
    return dict(sorted(out.items()))


def save_baseline(path: Path, current: dict[str, float]) -> None:
    """Write current metrics as the baseline.  An existing file keeps everything above its
    `metrics:` section verbatim (the tolerances and the comments that justify them)."""
    head = "tolerances: {}\n"
    if Path(path).exists():
        load_baseline(path)  # refuse to rewrite a malformed file
        lines = Path(path).read_text().splitlines(keepends=True)
        cut = next((i for i, line in enumerate(lines) if line.startswith("metrics:")), len(lines))
        head = "".join(lines[:cut])
    Path(path).write_text(head + yaml.safe_dump({"metrics": current}, sort_keys=False))