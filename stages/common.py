"""Small helpers every science package shares, and the contact-sequence schema."""
from __future__ import annotations

import contextlib
import os
import sys
from typing import Mapping, Sequence

# The contact-sequence schema (DESIGN, "Science contracts"): beside `images` (N,H,W) and
# `reference` (H,W), the per-frame arrays a sequence carries, each (N,...) along the frame
# axis: forces (N,3) N and torques (N,3) N m, depth (N,) mm and its normalised depth, which
# frames load the skin, the indenter tip's position (N,3) and lateral shift (N,2) mm, the
# motion phase (0 press, 1 shear out, 2 shear back, 3 release), contact and indenter ids,
# the location-paired frames (and their motion position), and `frame`, which names a location
# alike in every sensor.  Every node that makes frames from frames copies the ones it has.
LABEL_KEYS = ("force", "torque", "depth", "normalised_depth", "loading", "position", "shift", "phase",
              "contact_id", "indenter_id", "paired", "paired_position", "frame")


def attrs_of(art) -> dict:
    """An input's attributes: a store artifact's `.attrs` (nested values decoded), or the
    "attrs" entry of a node's output dict (tests and direct calls pass those)."""
    attrs = getattr(art, "attrs", None)
    if attrs is None and isinstance(art, Mapping):
        attrs = art.get("attrs", {})
    return dict(attrs or {})


def default_threads() -> int:
    """Threads of torch (and, in a pipeline run, of every numeric library: node_threads):
    $GENFORCE_TORCH_THREADS, else 1.

    Fixed, not the machine's core count, so that a node's result does not depend on the
    executor it ran in (torch's float reductions change with the thread count, and a model
    trained on 2 threads differs from one trained on 1).  One is also the fastest choice when
    the pipeline shares 2 cores between nodes: measured by benchmarks/force.py while other
    processes were busy, a second thread made training 10x slower (busy-waiting OpenMP
    threads), and on an idle machine it gains at most ~1.5x."""
    env = os.environ.get("GENFORCE_TORCH_THREADS", "").strip()
    return max(1, int(env)) if env else 1


def check_option(what: str, value, options: Sequence) -> None:
    """An option value a node cannot use is bad input: one line naming it and the options."""
    if value not in tuple(options):
        raise InputError(f"{what} must be one of {', '.join(map(str, options))}, got {value!r}")


class InputError(ValueError):
    """Bad input a node finds: a param of the right type whose value it cannot use (an unknown
    indenter, an empty list of depths), or a file it reads that is missing or malformed.  The
    engine reports it in one line (exit 2) naming the culprit, not as the node's crash."""
    user_error = True


def marker_images(x, what: str, ndims=(2, 3)):
    """x as uint8 marker images (0/255) of one of `ndims` dimensions ((H,W) or (N,H,W)), or a
    ValueError naming `what` and what was expected: float images (0..1 or 0..255 alike) and
    values outside 0..255 are refused, not cast to garbage; bool images become 0/255."""
    import numpy as np
    a = np.asarray(x)
    if a.ndim not in ndims:
        shapes = " or ".join({2: "(H,W)", 3: "(N,H,W)", 4: "(B,T,H,W)"}[n] for n in ndims)
        raise ValueError(f"{what}: expected {shapes} marker images, got shape {a.shape}")
    if a.dtype == bool:
        return a.astype(np.uint8) * 255
    if a.dtype != np.uint8:
        if not np.issubdtype(a.dtype, np.integer):
            raise ValueError(f"{what}: expected uint8 marker images (0/255), got {a.dtype}")
        if a.size and (a.min() < 0 or a.max() > 255):
            raise ValueError(f"{what}: values {a.min()}..{a.max()} outside the marker images' 0..255")
    return a.astype(np.uint8, copy=False)


class DeviceChoiceError(ValueError):
    """$GENFORCE_DEVICE names no device this machine has: the engine reports it in one line
    (exit 2), like bad input, rather than as a node's crash."""
    user_error = True


def torch_device():
    """Where the networks train and predict in batches: $GENFORCE_DEVICE when set ("cpu",
    "cuda", "cuda:1", ...), else the GPU when torch sees one, else the CPU.

    A GPU's float arithmetic differs from the CPU's, so a model trained on one differs in its
    last bits from one trained on the other; the store does not tell them apart.  Set
    GENFORCE_DEVICE=cpu on a GPU machine to train as a CPU machine does (bit for bit where the
    CPU type and the torch build are the same too)."""
    import torch
    name = os.environ.get("GENFORCE_DEVICE", "").strip()
    if not name:
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    try:
        dev = torch.device(name)
    except RuntimeError as err:
        raise DeviceChoiceError(f"GENFORCE_DEVICE={name!r} is not a torch device (cpu, cuda, cuda:1, ...)") from err
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise DeviceChoiceError(f"GENFORCE_DEVICE={name!r} but torch sees no CUDA device on this machine")
    if dev.type == "cuda" and dev.index is not None and dev.index >= torch.cuda.device_count():
        raise DeviceChoiceError(f"GENFORCE_DEVICE={name!r} but torch sees {torch.cuda.device_count()} "
                                f"CUDA device(s) on this machine (cuda:0 .. cuda:{torch.cuda.device_count() - 1})")
    if dev.type not in ("cpu", "cuda"):
        raise DeviceChoiceError(f"GENFORCE_DEVICE={name!r}: only cpu and cuda devices are supported")
    return dev


@contextlib.contextmanager
def torch_threads(n: int | None = None):
    """Run torch on `n` threads (default: :func:`default_threads`), restoring the setting afterwards."""
    import torch
    old = torch.get_num_threads()
    torch.set_num_threads(max(1, int(n or default_threads())))
    try:
        yield
    finally:
        torch.set_num_threads(old)


# read by the libraries a node imports: OpenMP (torch, scikit-learn), OpenBLAS and MKL (numpy,
# scipy, OpenCV's own OpenBLAS) and OpenCV's thread pool
THREAD_VARS = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "OPENCV_FOR_THREADS_NUM")


class KernelChoiceError(RuntimeError):
    """numpy runs CPU-specific kernels in a process that runs nodes: one line, exit 2."""
    user_error = True


def numpy_kernels_fixed() -> None:
    """Refuse to run a node where numpy chose its kernels by this CPU: numpy was imported
    before `stages` set NPY_DISABLE_CPU_FEATURES (stages/__init__.py), e.g. in a Dask worker
    started without it, and the node's floats would differ in their last bits from another
    machine's under the same cache key."""
    from stages import NUMPY_DISPATCH_OFF, X86_64
    if not X86_64:
        return
    from numpy._core._multiarray_umath import __cpu_dispatch__, __cpu_features__
    on = [f for f in __cpu_dispatch__ if __cpu_features__.get(f)]
    if on:
        raise KernelChoiceError(
            f"numpy runs CPU-specific kernels ({', '.join(on)}) in this process: start it (a Dask "
            f"worker: its environment) with NPY_DISABLE_CPU_FEATURES='{NUMPY_DISPATCH_OFF}', or "
            "import stages before numpy")


@contextlib.contextmanager
def node_threads(n: int | None = None):
    """Run a node with `n` threads (default: :func:`default_threads`) in every numeric library,
    whichever executor runs it; the pipeline runs each node inside this ([tool.pipeline]
    node_context in pyproject.toml).

    A float reduction split over threads changes with their count, and each library's own
    default is the machine's cores, or in a process pool the share its executor sets, so one
    cache key held two contents: flow_warp's InceptionV3 features (torch, outside a node's
    torch_threads) differed between the inline and the process executor.  Libraries the node
    imports read THREAD_VARS; those already loaded are set directly; all is restored after."""
    n = max(1, int(n or default_threads()))
    numpy_kernels_fixed()
    saved = {v: os.environ.get(v) for v in THREAD_VARS}
    os.environ.update({v: str(n) for v in THREAD_VARS})
    try:
        with contextlib.ExitStack() as stack:
            if "torch" in sys.modules:
                stack.enter_context(torch_threads(n))
            import cv2      # its CPU-dispatched kernels (and IPP's) off: the same bits on every CPU
            stack.callback(cv2.setUseOptimized, cv2.useOptimized())
            cv2.setUseOptimized(False)
            stack.callback(cv2.setNumThreads, cv2.getNumThreads())
            cv2.setNumThreads(n)
            if any(m in sys.modules for m in ("numpy", "scipy", "sklearn", "cv2", "torch")):
                from threadpoolctl import threadpool_limits
                stack.enter_context(threadpool_limits(n))
            yield
    finally:
        for var, value in saved.items():
            if value is None:
                os.environ.pop(var, None)
            else:
                os.environ[var] = value


TIMING_KEYS = frozenset({"seconds", "steps_per_s", "samples_per_s", "frames_per_s", "images_per_s"})


def split_timing(record: Mapping) -> tuple[dict, dict]:
    """(record without its timings, the timings): a training history, nested or not, split so
    that the timings go to a node's "timing" (provenance, outside the content digest: a re-run
    at another speed keeps its digest) and the rest to its attrs."""
    kept, timing = {}, {}
    for k, v in record.items():
        if isinstance(v, Mapping):
            kept[k], sub = split_timing(v)
            if sub:
                timing[k] = sub
        elif k in TIMING_KEYS:
            timing[k] = v
        else:
            kept[k] = v
    return kept, timing


def save_state(path: str, state: dict) -> None:
    """torch.save a training state to a temporary file and rename it over `path`: a kill
    mid-write leaves the previous file whole."""
    import torch
    tmp = f"{path}.tmp"
    torch.save(state, tmp)
    os.replace(tmp, path)


def load_state(path: str, check=None, *, stacklevel: int = 1) -> dict | None:
    """The training state save_state wrote at `path` (loaded with weights_only: tensors and
    plain values, no code), or None when there is none.  One that cannot be read, or that
    `check(state)` rejects by raising, is renamed <path>.bad with a warning (at `stacklevel`
    counted from load_state's caller) and None is returned: training starts over."""
    import warnings
    import torch
    if not os.path.exists(path):
        return None
    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
        if check is not None:
            check(state)
    except Exception as exc:  # noqa: BLE001 - any unreadable checkpoint: start over, keep it aside
        os.replace(path, f"{path}.bad")
        warnings.warn(f"checkpoint {path} set aside as .bad and training starts over: "
                      f"{type(exc).__name__}: {exc}", stacklevel=stacklevel + 1)
        return None
    return state
