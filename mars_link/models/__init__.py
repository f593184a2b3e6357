"""Models the coordinator and the world share: estimation, fault detection, trajectories, environment, batteries."""
