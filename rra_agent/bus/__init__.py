"""The bus: Zenoh session configuration and opening, the key-expression layout, wire messages,
limits and the receive preamble, heartbeats, failure reports, the tools' client library."""
