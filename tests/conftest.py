"""Every test trains and predicts on the CPU, on a GPU machine too: several tests compare
models trained twice bit for bit, which cuDNN's kernels do not promise, and the ci baseline's
figures are CPU figures.  (The pipeline itself uses a GPU when torch sees one;
stages.common.torch_device.)  GENFORCE_TEST_DEVICE=cuda runs them on the GPU instead, to
check the GPU paths: README, "The paper profile on a GPU"."""
import os

os.environ["GENFORCE_DEVICE"] = os.environ.get("GENFORCE_TEST_DEVICE", "cpu")
