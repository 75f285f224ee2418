"""msgspec Structs for every RRA model, their loaders and cross-reference validation."""
