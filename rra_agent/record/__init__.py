"""The run record: what a run's engines decided from, kept so that the decisions can be
re-run offline (``rra replay``), also against edited models (what-if).

- `rra_agent.record.format`: the record files (framed msgpack records) and their reader;
- `rra_agent.record.run`: a run folder's ``record/`` (the models of each version, the seal);
- `rra_agent.record.hooks`: what the engine processes call to record (cheap, never raising);
- `rra_agent.record.replay`: the offline re-run and its comparison (docs/recording.md).
"""
