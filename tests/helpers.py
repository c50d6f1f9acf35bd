"""Helpers shared by test folders (a plain module: `conftest` names clash across folders)."""
import importlib.util
from pathlib import Path

import numpy as np
import yaml

ROOT = Path(__file__).resolve().parents[1]


def drain(gen):
    """Run a streaming node to the end: (list of yielded chunks, the returned mapping)."""
    chunks = []
    while True:
        try:
            chunks.append(next(gen))
        except StopIteration as stop:
            return chunks, stop.value


def concat(chunks) -> dict:
    """The chunks joined along the frame axis (nested mappings joined key by key)."""
    out = {}
    for key, value in chunks[0].items():
        if isinstance(value, dict):
            out[key] = {k: np.concatenate([c[key][k] for c in chunks]) for k in value}
        else:
            out[key] = np.concatenate([c[key] for c in chunks])
    return out


def _merge(base: dict, overlay: dict) -> None:
    for k, v in overlay.items():
        if isinstance(v, dict):
            _merge(base[k], v)
        else:
            base[k] = v


def load_params(profile: str | None = None) -> dict:
    """params.yaml with a profile's overrides merged in (profiles only change values)."""
    params = yaml.safe_load((ROOT / "params.yaml").read_text())
    if profile:
        _merge(params, yaml.safe_load((ROOT / "params" / f"{profile}.yaml").read_text()))
    return params


def load_script(name: str):
    """A script of scripts/ (not a package) imported as a module, to test its functions."""
    spec = importlib.util.spec_from_file_location(name, ROOT / "scripts" / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def flat_pad(n: int = 17, size: float = 20.0) -> dict:
    """A deform artifact's pad keys for an undeformed n x n grid over a size x size mm pad."""
    g = (np.arange(n) - (n - 1) / 2) * size / (n - 1)
    return {"grid_x": g, "grid_y": g, "surface_z": np.zeros((n, n)), "on_pad": np.ones((n, n), bool)}


def gelsight_patterns(name: str = "gelsight-A-II", layout: str = "A-II") -> dict:
    """A patterns artifact holding one GelSight marker layout under `name`."""
    from stages.markers.patterns import gelsight_pattern
    m = gelsight_pattern(layout)
    return {f"markers/{name}/centers": m.centers, f"markers/{name}/axes": m.axes,
            f"markers/{name}/angles": m.angles, f"markers/{name}/pad_size_mm": np.array(m.pad_size_mm)}
