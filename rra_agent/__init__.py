"""rra-agent: Robotics Run-time Adaptation (Gherardi & Hochgeschwender, IROS 2015) on Zenoh."""

from rra_agent import _compat

__version__ = "0.2.0"

_compat.install()  # the old module paths of 0.1 still import, with a DeprecationWarning
