"""Integration tests against real autopilot SITL builds (see tests/sitl/conftest.py).

A package so that this directory's conftest.py does not take the module name ``conftest``
from tests/conftest.py, which the other test modules import from.
"""
