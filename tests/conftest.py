"""Every test trains and predicts on the CPU, on a GPU machine too: several tests compare
models trained twice bit for bit, which cuDNN's kernels do not promise, and the ci baseline's
figures are CPU figures.  (The pipeline itself uses a GPU when torch sees one;
stages.common.torch_device.)  GENFORCE_TEST_DEVICE=cuda runs them on the GPU instead, to
check the GPU paths, with TF32 off and torch's deterministic kernels: README, "GPU and
cluster"."""
import os

import stages  # noqa: F401  (before numpy: numpy's kernels the same on every CPU, stages/__init__.py)

os.environ["GENFORCE_DEVICE"] = os.environ.get("GENFORCE_TEST_DEVICE", "cpu")
if os.environ["GENFORCE_DEVICE"] != "cpu":
    os.environ.setdefault("CUBLAS_WORKSPACE_CONFIG", ":4096:8")     # cuBLAS's deterministic mode
    import torch
    torch.backends.cudnn.allow_tf32 = False
    torch.backends.cuda.matmul.allow_tf32 = False
    torch.use_deterministic_algorithms(True, warn_only=True)

# `make test` runs the suite in one pytest-xdist worker per core: torch in each takes its share
# of the cores, not all of them (two workers' OpenMP threads spinning on each other's cores slow
# both many times over)
_WORKERS = int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1"))
if _WORKERS > 1:
    import torch
    torch.set_num_threads(max(1, (os.cpu_count() or 1) // _WORKERS))
