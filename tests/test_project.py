"""The project's own graph, params and generated files stay consistent."""
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from pipeline import params as P
from pipeline.config import find_project

ROOT = Path(__file__).resolve().parents[1]


def pipeline(*args, check=True):
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    env.pop("PIPELINE_STORE", None)
    p = subprocess.run([sys.executable, "-m", "pipeline", *args], cwd=ROOT, env=env,
                       capture_output=True, text=True, timeout=600)
    if check and p.returncode:
        raise AssertionError(p.stdout + p.stderr)
    return p


def test_dvc_yaml_in_sync():
    p = pipeline("dvc", "--check", check=False)
    assert p.returncode == 0, "dvc.yaml is out of date: run `pipeline dvc` and commit it"


@pytest.mark.parametrize("profile", ["default", "ci", "paper"])
def test_profiles_load(profile):
    project = find_project(ROOT)
    params = P.load(project.params_file, profile, [], project.profiles_dir)
    project.load_graph().expand(params)  # every reference resolves


def test_ci_profile_runs_and_is_then_cached(tmp_path):
    store = str(tmp_path / "store")
    first = json.loads(pipeline("run", "--profile", "ci", "--json", "--store", store).stdout)
    assert {n["status"] for n in first["nodes"]} == {"ran"}
    again = json.loads(pipeline("run", "--profile", "ci", "--json", "--store", store).stdout)
    assert {n["status"] for n in again["nodes"]} == {"cached"}
    assert pipeline("verify", "--store", store).returncode == 0


def test_noop_run_imports_no_science(tmp_path):
    """Deciding that nothing is stale must not import torch, mitsuba, cv2 or even h5py."""
    store = str(tmp_path / "store")
    pipeline("run", "--profile", "ci", "--store", store)
    code = ("import sys; from pipeline.cli import main; "
            f"rc = main(['run', '--profile', 'ci', '--store', {store!r}]); "
            "heavy = sorted(m for m in ('torch', 'mitsuba', 'cv2', 'h5py', 'trimesh', 'scipy', 'numpy') "
            "if m in sys.modules); print('HEAVY', heavy); sys.exit(rc)")
    p = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True,
                       env={**os.environ, "PYTHONPATH": str(ROOT)})
    assert p.returncode == 0, p.stderr
    assert "HEAVY []" in p.stdout
