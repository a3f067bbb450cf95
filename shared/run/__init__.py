"""A run's settings and files: the config and its reference, the settings fingerprint, run
directories (rundir), figures (overview), progress lines, disks, atomic files, a process's
start-up (runtime), learned maps' files (mapfiles), ROS output (rosout, rosmaps) and compute slots."""
