"""The world: JSBSim rigid bodies, sensor models, the simulation clock and the process launcher."""
