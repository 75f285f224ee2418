"""The bus: Zenoh session configuration, the key-expression layout, wire messages, the Node SDK."""
