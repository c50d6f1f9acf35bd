import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).parent))
import toyproject  # noqa: E402


@pytest.fixture
def toy(tmp_path):
    return toyproject.make(tmp_path / "proj")
