"""swarmmap's common library: wire protocol, config, Zenoh bus, floor plans, sensing, models."""
