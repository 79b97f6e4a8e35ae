"""Helpers for the tests and the benchmarks that ship in no wheel.

The tests import them as ``support.*`` (pytest puts ``tests/`` on ``sys.path``); a benchmark under
``bench/`` puts ``tests/`` there itself before importing them.
"""
