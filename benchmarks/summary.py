"""Figures a benchmark hands to benchmarks/run_all.py for its summary table, and `drain`.

`record` appends one JSON line to the file named by the BENCH_SUMMARY environment variable;
without it (a benchmark run on its own) it does nothing.
"""
from __future__ import annotations

import json
import os


def record(bench: str, name: str, measured: str, ratio: float | None, target: str = "") -> None:
    """Note one figure: `measured` as printed, `ratio` the number a target such as ">= 0.7" is about."""
    path = os.environ.get("BENCH_SUMMARY")
    if not path:
        return
    row = {"bench": bench, "name": name, "measured": measured,
           "ratio": None if ratio is None else float(ratio), "target": target}
    with open(path, "a") as f:
        f.write(json.dumps(row) + "\n")


def drain(gen):
    """Run a streaming node (a generator) to the end, dropping its chunks: its returned value."""
    while True:
        try:
            next(gen)
        except StopIteration as stop:
            return stop.value
