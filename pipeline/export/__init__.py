"""Deployment of the trained calibrations: ONNX graphs, their metadata and manifest, and their checks."""
