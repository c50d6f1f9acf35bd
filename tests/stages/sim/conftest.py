"""The sensor and material catalogue as the nodes receive it, without the engine."""
import pytest

from tests.helpers import drain, load_params


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


@pytest.fixture(scope="session")
def run_node():
    """Drain a streaming node: gen -> (list of chunks, final mapping)."""
    return drain
