"""The paper's evaluation vehicle (Sec. IV): a simulated quadcopter and its control nodes.

- `rra_agent.sim.model`: the vehicle (MuJoCo rigid body + motor/rotor model, faults, sensor
  noise, crash detection); no bus.
- `rra_agent.sim.control`: trajectory, estimator, standard and Proploss controllers as pure
  classes, and `simulate`, the in-process closed loop used by the tests and
  ``tools/sweep_switch_delay.py``.
- `rra_agent.sim.nodes`: the components of ``scenarios/quadcopter`` as Nodes.

Nothing is imported here: the controller nodes never load MuJoCo (docs/quadcopter.md).
"""
