"""swarmmap's services (router, world, lidar, learner), the launcher and the command line."""
