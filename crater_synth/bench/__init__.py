"""Benchmarks (``crater-synth bench``, ``make bench``): performance measured, never asserted in tests.

- ``cli``: the command and its parts; ``renderer``: renders/s against the Cycles baselines;
  ``train``: training throughput and memory.
"""
