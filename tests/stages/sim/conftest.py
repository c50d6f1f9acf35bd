"""The sensor and material catalogue as the nodes receive it, without the engine."""
from pathlib import Path

import pytest
import yaml

ROOT = Path(__file__).resolve().parents[3]


def load_params(profile: str | None = None) -> dict:
    """params.yaml with a profile's overrides merged in (profiles only change values)."""
    params = yaml.safe_load((ROOT / "params.yaml").read_text())
    if profile:
        _merge(params, yaml.safe_load((ROOT / "params" / f"{profile}.yaml").read_text()))
    return params


def _merge(base: dict, overlay: dict) -> None:
    for k, v in overlay.items():
        if isinstance(v, dict):
            _merge(base[k], v)
        else:
            base[k] = v


def flatten(tree: dict, prefix: str = "") -> dict:
    """Nested node output -> the flat dataset names an artifact has ('meshes/cone/faces')."""
    out = {}
    for k, v in tree.items():
        name = f"{prefix}/{k}" if prefix else k
        out.update(flatten(v, name) if isinstance(v, dict) else {name: v})
    return out


@pytest.fixture(scope="session", name="load_params")
def load_params_fixture():
    """profile name (or None) -> merged params."""
    return load_params


@pytest.fixture(scope="session")
def params():
    return load_params()


@pytest.fixture(scope="session")
def ci_params():
    return load_params("ci")


@pytest.fixture(scope="session")
def indenter_artifact():
    from stages.sim.indenters import ALL_INDENTERS, indenter_set
    return flatten(indenter_set(list(ALL_INDENTERS)))


def _drain(gen):
    chunks = []
    while True:
        try:
            chunks.append(next(gen))
        except StopIteration as stop:
            return chunks, stop.value


@pytest.fixture(scope="session")
def run_node():
    """Drain a streaming node: gen -> (list of chunks, final mapping)."""
    return _drain
