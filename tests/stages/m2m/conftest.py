"""Tiny synthetic marker artifacts for the M2M tests.

Skins are simulation patterns (stages.markers.patterns) with their markers enlarged so that
they stay >= 3 px wide at SIZE px; every frame moves the marker centres by one smooth
synthetic displacement field (a Gaussian bump of shear plus a radial push), the same field
for every skin at the same `frame`, as a shared contact would.  Frames alternate between a
"seen" and an "unseen" indenter so that training and evaluation frames differ.
"""
import pytest
from m2m_synthetic import SKINS, marker_artifact


@pytest.fixture(autouse=True, scope="package")
def one_torch_thread():
    """Torch on one thread: on a shared 2-core machine two OpenMP threads spin on each other
    (a 15 s training took 5 minutes under load); restored afterwards."""
    import torch
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


@pytest.fixture(scope="session")
def skins():
    return {name: marker_artifact(name) for name in SKINS}
