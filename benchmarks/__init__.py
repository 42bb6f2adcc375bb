"""Speed and accuracy measurements (docs/benchmarks.md). Each one the docs show takes ``--quick``: a run
of seconds through every step, which the test suite makes (tests/test_benchmarks.py) so that none stops
working."""

QUICK = "a run of seconds through every step, for the test suite (its figures mean nothing)"
