"""Helpers shared by test folders (a plain module: `conftest` names clash across folders)."""
import importlib.util
from pathlib import Path

import numpy as np

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


def load_params(profile: str | None = None) -> dict:
    """params.yaml with a profile's overrides merged in and `extends` resolved, as the pipeline
    loads them."""
    from pipeline.params import load
    return load(ROOT / "params.yaml", profile, [], ROOT / "params")


def load_script(name: str):
    """A script of scripts/ (not a package) imported as a module, to test its functions."""
    spec = importlib.util.spec_from_file_location(name, ROOT / "scripts" / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def data_offset(dataset) -> int:
    """The file offset of an h5py dataset's first stored data byte, contiguous or chunked."""
    offset = dataset.id.get_offset()
    return offset if offset is not None else dataset.id.get_chunk_info(0).byte_offset
