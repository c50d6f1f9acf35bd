"""Choosing Mitsuba's variant: `llvm_ad_rgb` where Dr.Jit's LLVM backend works, else `scalar_rgb`.

Dr.Jit needs LLVM >= 17 at run time; with LLVM 15/16 it aborts the whole process ("Cannot
select ... fminimum") the first time it compiles a kernel, so a crash cannot be caught in
process.  `llvm_usable` therefore finds the newest libLLVM on the machine, points
DRJIT_LIBLLVM_PATH at it and renders a tiny scene in a subprocess first; the answer is cached
for the life of the process.  The variable is read when Dr.Jit first starts its LLVM backend,
so it has to be set before any llvm variant is used in this process (it is, here).

Dr.Jit's LLVM backend compiles its kernels for the CPU it runs on: AVX-512 machines get
16-wide vectors and other instructions (reciprocals, rounding) than AVX2 machines, so the
renders differ in their last bits and their marker masks in a few pixels.  The target is
therefore fixed (`PINNED_TARGET`: x86-64 with AVX2 and FMA, 8 lanes) on every machine that
has those, and the render nodes' cache keys name it (`render_target`, read at plan time):
two machines write one content under one key, and a machine that cannot run the pinned target
renders with scalar_rgb under another key.
"""
from __future__ import annotations

import contextlib
import functools
import glob
import os
import platform
import re
import subprocess
import sys
from typing import Mapping

MIN_LLVM = 17
# (cpu, features, vector width) every x86-64 machine with AVX2 and FMA compiles Dr.Jit's kernels for
PINNED_TARGET = ("haswell", "+sse4.2,+popcnt,+avx,+avx2,+fma,+f16c,+bmi,+bmi2,+lzcnt,+movbe", 8)
PINNED_NEEDS = ("avx2", "fma", "f16c", "bmi2", "movbe")     # /proc/cpuinfo flags
VARIANTS = {"llvm": "llvm_ad_rgb", "scalar": "scalar_rgb"}
_LIB_GLOBS = ("/usr/lib/x86_64-linux-gnu/libLLVM*.so*", "/usr/lib/aarch64-linux-gnu/libLLVM*.so*",
              "/usr/lib/llvm-*/lib/libLLVM*.so*", "/usr/lib64/libLLVM*.so*",
              "/usr/local/lib/libLLVM*.so*", "/opt/homebrew/opt/llvm/lib/libLLVM*.dylib")
_PROBE = """
import mitsuba as mi
mi.set_variant("llvm_ad_rgb")
scene = mi.load_dict({"type": "scene", "integrator": {"type": "aov", "aovs": "uv:uv,dd:depth"},
    "sensor": {"type": "perspective", "fov": 40,
               "to_world": mi.ScalarTransform4f().look_at(origin=[0, 0, -4], target=[0, 0, 0], up=[0, -1, 0]),
               "film": {"type": "hdrfilm", "width": 4, "height": 4}},
    "shape": {"type": "rectangle"}})
print("ok", float(mi.render(scene).numpy().sum()))
"""


def llvm_version(path: str) -> int:
    """Major version from a libLLVM file name (libLLVM-19.so, libLLVM.so.19.1); 0 if none."""
    m = re.search(r"libLLVM(?:-(\d+)|\.so\.(\d+)|\.(\d+)\.dylib)", os.path.basename(path))
    return int(next(g for g in m.groups() if g)) if m else 0


def find_libllvm() -> str | None:
    """The newest libLLVM >= 17 on this machine (DRJIT_LIBLLVM_PATH wins when set)."""
    if os.environ.get("DRJIT_LIBLLVM_PATH"):
        return os.environ["DRJIT_LIBLLVM_PATH"]
    found = {p for pattern in _LIB_GLOBS for p in glob.glob(pattern)}
    best = max(found, key=lambda p: (llvm_version(p), p), default=None)
    return best if best and llvm_version(best) >= MIN_LLVM else None


@functools.cache
def llvm_usable() -> bool:
    """Whether the llvm variant renders here (probed once per process, in a subprocess)."""
    lib = find_libllvm()
    if lib is None:
        return False
    env = dict(os.environ, DRJIT_LIBLLVM_PATH=lib)
    try:
        out = subprocess.run([sys.executable, "-c", _PROBE], env=env, capture_output=True,
                             text=True, timeout=180)
    except (OSError, subprocess.TimeoutExpired):
        return False
    if out.returncode != 0 or not out.stdout.startswith("ok"):
        return False
    os.environ["DRJIT_LIBLLVM_PATH"] = lib
    return True


def _cpu_flags() -> set[str]:
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("flags"):
                    return set(line.split(":", 1)[1].split())
    except OSError:
        pass
    return set()


def render_target(backend: str) -> dict:
    """What a render's content depends on, decided at plan time without importing Mitsuba
    (a Listing of the render nodes, so it is part of their cache keys): {"backend": "scalar"},
    or {"backend": "llvm", "target": "<cpu>/<features>/<width>", "llvm": <major>}.  "auto" is
    llvm where a libLLVM >= 17 is found and the CPU runs the pinned target, else scalar;
    "llvm" is refused where it is not so."""
    from stages.common import InputError
    check = ("auto", "llvm", "scalar")
    if backend not in check:
        raise InputError(f"render.backend {backend!r}: expected one of {', '.join(check)}")
    if backend == "scalar":
        return {"backend": "scalar"}
    from stages import X86_64
    lib = find_libllvm()
    if X86_64:
        runs = set(PINNED_NEEDS) <= _cpu_flags()
        target = "/".join(map(str, PINNED_TARGET))
    else:       # no pinned target elsewhere: the key names the machine kind the kernels are built for
        runs, target = True, f"host/{platform.machine()}"
    if lib is not None and runs:
        return {"backend": "llvm", "target": target, "llvm": llvm_version(lib)}
    if backend == "llvm":
        why = f"no libLLVM >= {MIN_LLVM} found" if lib is None else \
            f"this CPU lacks {', '.join(sorted(set(PINNED_NEEDS) - _cpu_flags()))} for the pinned target"
        raise InputError(f"render.backend 'llvm': {why}; use 'auto' or 'scalar'")
    return {"backend": "scalar"}


def resolve_backend(backend) -> str:
    """"auto" -> "llvm" when usable, else "scalar"; "llvm" must be usable; "scalar" always is.
    A `render_target` mapping resolves to its backend, which must then be usable."""
    if isinstance(backend, Mapping):
        chosen = backend.get("backend")
        if chosen == "llvm" and not llvm_usable():
            raise ValueError("render target llvm (chosen at plan time) but Dr.Jit's LLVM backend "
                             "fails its probe render here; run with -p render.backend=scalar")
        backend = chosen
    if backend not in ("auto", "llvm", "scalar"):
        raise ValueError(f"render backend {backend!r}: expected 'auto', 'llvm' or 'scalar'")
    if backend == "scalar":
        return "scalar"
    if llvm_usable():
        return "llvm"
    if backend == "llvm":
        raise ValueError("render backend 'llvm': Dr.Jit's LLVM backend is unusable here "
                         f"(no libLLVM >= {MIN_LLVM} found, or the probe render failed); "
                         "use backend 'auto' or 'scalar'")
    return "scalar"


def mitsuba(backend: str):
    """The mitsuba module with the backend's variant set ("llvm" or "scalar", resolved); llvm
    compiles for the pinned target."""
    import mitsuba as mi
    variant = VARIANTS[backend]
    if mi.variant() != variant:
        mi.set_variant(variant)
    if backend == "llvm":
        pin_llvm_target()
    return mi


@functools.cache
def _drjit_core():
    import ctypes
    import drjit
    lib = ctypes.CDLL(os.path.join(os.path.dirname(drjit.__file__), "libdrjit-core.so"))
    # Dr.Jit's C++ API (drjit-core's jit.h), not exposed to Python
    set_target = lib._Z19jit_llvm_set_targetPKcS0_j
    set_target.argtypes = [ctypes.c_char_p, ctypes.c_char_p, ctypes.c_uint32]
    set_target.restype = None
    cpu, features, width = lib._Z19jit_llvm_target_cpuv, lib._Z24jit_llvm_target_featuresv, \
        lib._Z21jit_llvm_vector_widthv
    cpu.restype = features.restype = ctypes.c_char_p
    width.restype = ctypes.c_uint32
    return set_target, cpu, features, width


def llvm_target() -> tuple[str, str, int]:
    """The (cpu, features, vector width) Dr.Jit's LLVM backend compiles for now."""
    _, cpu, features, width = _drjit_core()
    return cpu().decode(), features().decode(), int(width())


def pin_llvm_target() -> None:
    """Compile Dr.Jit's LLVM kernels for PINNED_TARGET on x86-64 (once the llvm variant is
    set: the backend must have started); elsewhere the host's target stays."""
    from stages import X86_64
    if not X86_64:
        return
    if llvm_target() != PINNED_TARGET:
        cpu, features, width = PINNED_TARGET
        _drjit_core()[0](cpu.encode(), features.encode(), width)
        if llvm_target() != PINNED_TARGET:
            raise RuntimeError(f"Dr.Jit kept its LLVM target {llvm_target()} instead of {PINNED_TARGET}")


@contextlib.contextmanager
def thread_count(n: int | None):
    """Dr.Jit's worker threads (Mitsuba's, both variants) set to n for the duration, then
    restored; None leaves them alone."""
    import drjit as dr
    old = dr.thread_count()
    if n:
        dr.set_thread_count(int(n))
    try:
        yield
    finally:
        dr.set_thread_count(old)
