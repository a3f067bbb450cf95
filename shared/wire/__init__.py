"""What crosses the network: the wire protocol and its codec (protocol), Zenoh sessions (bus), the
run's credentials and access policy (secrets), the registry of the run's services (services),
compressed States (compression), robot claims (claims) and the routers' mesh (mesh)."""
