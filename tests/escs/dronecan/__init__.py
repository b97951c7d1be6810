"""Tests of the DroneCAN ESC family (bridge/escs/dronecan/); ../__init__.py says why a package."""
