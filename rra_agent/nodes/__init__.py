"""Component implementations shipped with rra-agent (generic nodes and the example systems')."""
