"""ftcal: in-situ calibration of 6-axis force/torque sensors on humanoid robots."""

from pipeline.core.kernels import pin as _pin_kernels

__version__ = "0.1.0"

# before numpy, OpenBLAS and MKL choose their kernels: the same bits on every x86-64 machine with AVX2
_pin_kernels()
