"""The ``rra`` command line."""

from rra_agent.cli.commands import main

__all__ = ["main"]
