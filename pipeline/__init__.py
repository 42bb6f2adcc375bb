"""ftcal: in-situ calibration of 6-axis force/torque sensors on humanoid robots."""

__version__ = "0.1.0"
