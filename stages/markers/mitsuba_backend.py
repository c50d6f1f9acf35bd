"""Choosing Mitsuba's variant: `llvm_ad_rgb` where Dr.Jit's LLVM backend works, else `scalar_rgb`.

Dr.Jit needs LLVM >= 17 at run time; with LLVM 15/16 it aborts the whole process ("Cannot
select ... fminimum") the first time it compiles a kernel, so a crash cannot be caught in
process.  `llvm_usable` therefore finds the newest libLLVM on the machine, points
DRJIT_LIBLLVM_PATH at it and renders a tiny scene in a subprocess first; the answer is cached
for the life of the process.  The variable is read when Dr.Jit first starts its LLVM backend,
so it has to be set before any llvm variant is used in this process (it is, here).
"""
from __future__ import annotations

import contextlib
import functools
import glob
import os
import re
import subprocess
import sys

MIN_LLVM = 17
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


def resolve_backend(backend: str) -> str:
    """"auto" -> "llvm" when usable, else "scalar"; "llvm" must be usable; "scalar" always is."""
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
    """The mitsuba module with the backend's variant set ("llvm" or "scalar", resolved)."""
    import mitsuba as mi
    variant = VARIANTS[backend]
    if mi.variant() != variant:
        mi.set_variant(variant)
    return mi


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
