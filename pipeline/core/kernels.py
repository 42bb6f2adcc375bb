"""The numerical kernels of every ftcal process, pinned: the same data and params give the same bits on any
x86-64 machine with AVX2 (Intel since 2013, AMD since 2015), whatever its vendor, whatever else its CPU has
(AVX-512, AMX) and however many cores it has.

numpy, OpenBLAS, MKL and ATen choose their kernels when they start, by the CPU's vendor and instruction
sets, and kernels of other vector widths round differently. On an AVX-512 machine numpy's float64 sine and
cosine (the simulated motions) and OpenBLAS's matrix products (the baselines' normal equations, the labels'
transforms) end in other last bits than on an AVX2 machine; MKL (torch's float32 matrix products) takes
another code path on an AMD CPU than on an Intel one. The training then grows a last-bit difference into
another network within an epoch, and two workstations of a lab deploy different calibrations from the
same logs (measured on the default data: r_arm_ft deployed nn13 on one machine, nn7 on another). `pin`
makes each library take the same kernels on every machine that has AVX2:

- numpy's ufuncs: ``NPY_DISABLE_CPU_FEATURES`` lists the AVX-512 dispatch targets (numpy 2.4's names and the
  older ones: numpy ignores the names it does not know, with a hidden ImportWarning);
- OpenBLAS, numpy's linear algebra: ``OPENBLAS_CORETYPE=Haswell``, and ``OPENBLAS_NUM_THREADS=1`` (its
  matrix products split the work by the number of cores and round by the split: the stages run their
  parallel work in processes, `pipeline.core.parallel`);
- MKL: ``MKL_CBWR=COMPATIBLE``, the one branch of MKL's conditional numerical reproducibility that is the
  same on Intel and non-Intel CPUs (its AVX2 branch is Intel's only: on an AMD CPU MKL falls back to its
  automatic choice, measured on an EPYC). No branch makes MKL's products independent of the number of
  threads on an AMD CPU, so a network trains on one thread (`pipeline.calib.training.one_thread`);
- ATen's own kernels (``ATEN_CPU_CAPABILITY=avx2``) and oneDNN (``ONEDNN_MAX_CPU_ISA=AVX2``): the AVX2 ones,
  as on an AVX2 machine (they gave the same networks as their AVX-512 ones on the default data; pinned so
  that an op that would not, does).

Each variable is read once, when its library loads (numpy, OpenBLAS, ATen) or first computes (MKL, oneDNN):
`pin` runs when the `pipeline` package is imported, which in an ``ftcal`` process (and a benchmark's) comes
before any of them. A variable already set is left as it is (a deliberate choice, or the emulation of
another machine); ``FTCAL_KERNELS=native`` pins nothing (each library's fastest kernels for this CPU;
results then depend on the machine). On a CPU without AVX2, or not x86-64, nothing is pinned either: there
the last bits can differ, which training's decisions are made to tolerate (docs/models.md, "Same data,
same params, another machine").
"""

from __future__ import annotations

import os
import platform
from pathlib import Path

ENV_SWITCH = "FTCAL_KERNELS"  # "native": pin nothing
# numpy >= 2.4 dispatches on psABI groups (X86_V4 = AVX-512 F/CD/BW/DQ/VL), earlier ones on feature names
NUMPY_AVX512 = (
    "X86_V4 AVX512_ICL AVX512_SPR AVX512F AVX512CD AVX512_KNL AVX512_KNM AVX512_SKX AVX512_CLX AVX512_CNL"
)
PINS = {
    "NPY_DISABLE_CPU_FEATURES": NUMPY_AVX512,
    "OPENBLAS_CORETYPE": "Haswell",
    "OPENBLAS_NUM_THREADS": "1",
    "MKL_CBWR": "COMPATIBLE",
    "ATEN_CPU_CAPABILITY": "avx2",
    "ONEDNN_MAX_CPU_ISA": "AVX2",
}


def cpu_has_avx2(cpuinfo: Path = Path("/proc/cpuinfo")) -> bool:
    """Whether this is an x86-64 CPU with AVX2 and FMA (Linux: read from `cpuinfo`; elsewhere: False)."""
    if platform.machine().lower() not in ("x86_64", "amd64"):
        return False
    try:
        text = cpuinfo.read_text(errors="replace")
    except OSError:
        return False
    for line in text.splitlines():
        if line.startswith("flags"):
            flags = set(line.split(":", 1)[1].split())
            return {"avx2", "fma"} <= flags
    return False


def pin(environ: dict[str, str] | None = None) -> dict[str, str]:
    """Set the variables of `PINS` that are not set yet in `environ` (default: this process's environment),
    on an x86-64 CPU with AVX2 unless ``FTCAL_KERNELS=native``; return those it set."""
    env = os.environ if environ is None else environ
    if env.get(ENV_SWITCH, "").strip().lower() == "native" or not cpu_has_avx2():
        return {}
    added = {k: v for k, v in PINS.items() if k not in env}
    env.update(added)
    return added
