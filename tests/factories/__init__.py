"""Shared test helpers, one home each, grouped by what they make (import them from their submodule):

- labelled: labelled tables of a leg sensor and the r_foot pair, the pair's transforms
- params: params.yaml files with small train, ingest and evaluate sections
- logs: synthetic MCAP logs and the ingest settings that read them, logs rewritten in other layouts
- dumper: the recorded YARP dataDumper run and the tolerances of the dumper's printed numbers
- readback: MCAP logs read back by mcap's own reader and mcap_ros2's decoder
- reports: evaluate's outputs (the synthetic groups evaluated, metrics naming the recommended model)
- physics: physics references (per-link Newton-Euler, Pinocchio's own model, momentum balance)
- oracles: the iDynTree oracle and the sides of a sensor's cut from the URDF
- sensors: synthetic sensors of the calibration tests (a creeping reading, a free arm)
- docs: README.md, docs/ and dvc.yaml read as data (their commands, stages, tracked files)
"""
