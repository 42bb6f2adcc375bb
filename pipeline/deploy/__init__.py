"""Deployment tests A, B, C (thesis chapter 6) of the exported calibration on logs no model has seen."""
