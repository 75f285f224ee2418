"""The processes of an RRA system: context monitor, adaptation engine, run-time resolution
engine (with its supervisor), host agent."""
