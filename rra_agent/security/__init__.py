"""Zero-trust bus security: a system CA with per-host, per-role certificates (`certs`) for
Zenoh mTLS, and the Zenoh access-control configuration generated from the system model
(`acl`). Both use Zenoh's own TLS and ACL settings; nothing is layered on top."""
