"""The pure core: feature semantics, resolution, rule evaluation, conflict analysis.

Nothing here does I/O or imports zenoh, mujoco, rerun or the shell packages (bus, agents,
sim, viz, scenario, cli): plain values in, plain values out.
"""
