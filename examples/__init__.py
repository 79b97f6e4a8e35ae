"""Examples that run: each module is used as the docs show, and a test runs it (tests/test_own_policy.py).

Not part of the installed ``agos`` package: run them from the repository root, or put the root on
``PYTHONPATH``.
"""
