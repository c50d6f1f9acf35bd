"""The science of GenForce: pure functions the pipeline's graph (stages.graph) wires up.

Numeric libraries choose SIMD kernels by the CPU they run on, and the kernels' last bits
differ (numpy's float exp and power under AVX-512 against AVX2), so one cache key would hold
two contents on two machines.  numpy reads its choice when it is first imported, so it is
fixed here, before any module of the science imports it: every dispatched kernel off, the
baseline's on every x86-64 machine.  OpenCV and Dr.Jit are fixed at run time
(stages.common.node_threads, stages.markers.mitsuba_backend)."""
import os
import platform
import sys

# numpy >= 2.4's dispatched x86 feature groups (numpy.show_runtime); the baseline is X86_V2
NUMPY_DISPATCH_OFF = "X86_V3 X86_V4 AVX512_ICL AVX512_SPR"
X86_64 = platform.machine().lower() in ("x86_64", "amd64")   # where the kernels are pinned

if X86_64 and "numpy" not in sys.modules:
    os.environ.setdefault("NPY_DISABLE_CPU_FEATURES", NUMPY_DISPATCH_OFF)
