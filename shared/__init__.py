"""swarmmap's common library, by concern: wire (what crosses the network), world (plans, sensing,
logs), learning (the models), run (settings and files); api (swarmmap from Python) and plugins
(parts found through entry points) are its doors."""
