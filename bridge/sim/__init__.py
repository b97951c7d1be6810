"""The simulation around the ESCs: motor models, the runner that puts each family's simulated
ESCs (bridge/escs/<family>/sim.py) on a bus, load generators, and the demo's simulated autopilot."""
