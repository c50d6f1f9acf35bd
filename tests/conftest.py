"""Every test trains and predicts on the CPU, on a GPU machine too: several tests compare
models trained twice bit for bit, which cuDNN's kernels do not promise, and the ci baseline's
figures are CPU figures.  (The pipeline itself uses a GPU when torch sees one;
stages.common.torch_device.)  GENFORCE_TEST_DEVICE=cuda runs them on the GPU instead, to
check the GPU paths, with TF32 off and torch's deterministic kernels: README, "GPU and
cluster"."""
import os

os.environ["GENFORCE_DEVICE"] = os.environ.get("GENFORCE_TEST_DEVICE", "cpu")
if os.environ["GENFORCE_DEVICE"] != "cpu":
    os.environ.setdefault("CUBLAS_WORKSPACE_CONFIG", ":4096:8")     # cuBLAS's deterministic mode
    import torch
    torch.backends.cudnn.allow_tf32 = False
    torch.backends.cuda.matmul.allow_tf32 = False
    torch.use_deterministic_algorithms(True, warn_only=True)
