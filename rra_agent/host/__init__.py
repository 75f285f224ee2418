"""One machine's side of a system: the host agent, its supervisor, its process table and the
fork server that starts node processes."""
