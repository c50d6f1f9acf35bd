"""stages.common: the timing split every training node uses."""
from stages.common import split_timing


def test_split_timing_moves_only_timings_at_every_depth():
    history = {"loss": [3.0, 2.0], "seconds": 4.5, "steps": 2,
               "genforce": {"pretrain": {"loss": [1.0], "frames_per_s": 80.0, "contacts": 9},
                            "finetune": {"loss": [0.5]}}}
    kept, timing = split_timing(history)
    assert kept == {"loss": [3.0, 2.0], "steps": 2,
                    "genforce": {"pretrain": {"loss": [1.0], "contacts": 9}, "finetune": {"loss": [0.5]}}}
    assert timing == {"seconds": 4.5, "genforce": {"pretrain": {"frames_per_s": 80.0}}}
    assert history["seconds"] == 4.5                                   # the input is left alone


def test_torch_device_follows_GENFORCE_DEVICE_and_names_a_bad_one(monkeypatch):
    import pytest
    import torch
    from stages.common import torch_device
    from stages.m2m.model import device
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    monkeypatch.delenv("GENFORCE_DEVICE", raising=False)
    assert torch_device() == torch.device("cpu") == device()
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    assert torch_device() == torch.device("cuda") == device()          # a GPU is used when seen
    monkeypatch.setenv("GENFORCE_DEVICE", "cpu")
    assert torch_device() == torch.device("cpu")                       # ... unless told otherwise
    monkeypatch.setattr(torch.cuda, "device_count", lambda: 2)
    monkeypatch.setenv("GENFORCE_DEVICE", "cuda:1")
    assert torch_device() == torch.device("cuda", 1)
    monkeypatch.setenv("GENFORCE_DEVICE", "cuda:2")
    with pytest.raises(ValueError, match=r"'cuda:2' but torch sees 2 CUDA device\(s\) on this machine \(cuda:0 .. cuda:1\)"):
        torch_device()
    monkeypatch.setenv("GENFORCE_DEVICE", "cuda:1")
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    with pytest.raises(ValueError, match=r"GENFORCE_DEVICE='cuda:1' but torch sees no CUDA device") as err:
        torch_device()
    assert err.value.user_error is True                 # the engine's one-line error, exit 2
    monkeypatch.setenv("GENFORCE_DEVICE", "gpu0")
    with pytest.raises(ValueError, match=r"GENFORCE_DEVICE='gpu0' is not a torch device"):
        torch_device()
    monkeypatch.setenv("GENFORCE_DEVICE", "meta")
    with pytest.raises(ValueError, match=r"GENFORCE_DEVICE='meta': only cpu and cuda"):
        torch_device()


def test_node_threads_pins_every_numeric_library_and_restores_them(monkeypatch):
    """Inside: torch, OpenCV and the BLAS/OpenMP pools on default_threads() threads, and the
    variables the libraries a node imports read; after: everything as it was."""
    import os
    import cv2
    import numpy  # noqa: F401 - loads OpenBLAS
    import torch
    from threadpoolctl import threadpool_info
    from stages.common import THREAD_VARS, node_threads
    monkeypatch.setenv("GENFORCE_TORCH_THREADS", "1")
    monkeypatch.setenv("OMP_NUM_THREADS", "2")
    monkeypatch.delenv("OPENCV_FOR_THREADS_NUM", raising=False)
    cv2.setNumThreads(2)
    torch.set_num_threads(2)
    before = {(p["internal_api"], p["filepath"]): p["num_threads"] for p in threadpool_info()}
    with node_threads():
        assert [os.environ[v] for v in THREAD_VARS] == ["1"] * len(THREAD_VARS)
        assert cv2.getNumThreads() == 1 and torch.get_num_threads() == 1
        assert {p["num_threads"] for p in threadpool_info()} == {1}
    assert os.environ["OMP_NUM_THREADS"] == "2" and "OPENCV_FOR_THREADS_NUM" not in os.environ
    assert cv2.getNumThreads() == 2 and torch.get_num_threads() == 2
    assert {(p["internal_api"], p["filepath"]): p["num_threads"] for p in threadpool_info()} == before
