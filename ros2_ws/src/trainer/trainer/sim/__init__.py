"""The simulator as a data source beyond one process: rollout workers on Ray actors."""
