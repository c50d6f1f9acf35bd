"""Fixtures of the force tests (helpers in force_synthetic.py).

The test models are tiny: one torch thread runs them fastest, and does not fight other
processes for the cores."""
import os

import pytest
import torch
from force_synthetic import TINY, blob_contacts

os.environ["GENFORCE_TORCH_THREADS"] = "1"
torch.set_num_threads(1)


@pytest.fixture(scope="session")
def blobs():
    return blob_contacts


@pytest.fixture(scope="session")
def tiny_config():
    return dict(TINY)
