"""Scenarios: timed injections and expectations run against a real system (paper Sec. III).

- `rra_agent.scenario.model`: the ``*.scenario.yaml`` Structs and the loader (located errors);
- `rra_agent.scenario.expectations`: the expectation language, parsed and evaluated purely;
- `rra_agent.scenario.runner`: runs a case under ``rra up`` and records the bus;
- `rra_agent.cli.test`: ``rra test``; `rra_agent.scenario.plugin`: the pytest plugin.

See docs/scenarios.md.
"""
