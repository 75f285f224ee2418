"""rra-agent: Robotics Run-time Adaptation (Gherardi & Hochgeschwender, IROS 2015) on Zenoh."""

__version__ = "0.1.0"
