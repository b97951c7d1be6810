"""Simulated ESCs (CKESC, Flipsky FT) with motor models, and the simulated autopilot of the demo."""
