"""The engines of the adaptation loop (paper Fig. 1), each its own process: the Context
Monitor, the Adaptation Engine and the Run-time Resolution Engine with its planner/executor."""
