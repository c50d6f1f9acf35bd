"""Every test trains and predicts on the CPU, on a GPU machine too: several tests compare
models trained twice bit for bit, which cuDNN's kernels do not promise, and the ci baseline's
figures are CPU figures.  (The pipeline itself uses a GPU when torch sees one;
stages.common.torch_device.)"""
import os

os.environ["GENFORCE_DEVICE"] = "cpu"
