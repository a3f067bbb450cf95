#!/bin/sh
# The entrypoint of every swarmmap container: `swarmmap ARGS`, as the owner of the run directory.
#
#   swarmmap-entrypoint ARGS              swarmmap ARGS
#   swarmmap-entrypoint --start-run ARGS  first the start of a run, then swarmmap ARGS (compose's recorder)
#
# Started as root (compose's default user) with SWARMMAP_RUN_DIR set, it runs swarmmap as the
# owner of that directory, so that a run's files belong to whoever owns the run, not to root
# (rootless engines map root to the invoking user already; compose's `user:` skips all this).
# The start of a run (compose's first step: the other services wait for it) gives the runs
# folder and the run directory, when the engine has just made them (root's and empty), to the
# owner of /etc/swarmmap/compose.yaml (compose mounts its file there: the user who cloned the
# repository), then, as that user, runs `python -m swarmmap.services.claim start` (refuses a run
# directory holding another run, writes config.yaml and the credentials, forgets the robot
# claims of an earlier `up`) and marks the container started for compose's healthcheck.
set -eu
started=/tmp/swarmmap-started   # in the container's own file system: gone with the container
run_dir=${SWARMMAP_RUN_DIR:-}

adopt() {  # adopt DIR OWNER: give DIR to OWNER when the engine made it for a bind mount
    if [ -d "$1" ] && [ "$(stat -c %u:%g "$1")" = 0:0 ] && [ -z "$(ls -A "$1")" ]; then chown "$2" "$1"; fi
}

if [ "${1:-}" = --start-run ]; then
    rm -f "$started"
    if [ "$(id -u)" = 0 ] && [ -n "$run_dir" ] && [ -e /etc/swarmmap/compose.yaml ]; then
        owner=$(stat -c %u:%g /etc/swarmmap/compose.yaml)
        adopt "$(dirname "$run_dir")" "$owner"
        [ -e "$run_dir" ] || setpriv --reuid "${owner%:*}" --regid "${owner#*:}" --clear-groups mkdir -p "$run_dir" \
            || mkdir -p "$run_dir"
        adopt "$run_dir" "$owner"
    fi
fi
if [ "$(id -u)" = 0 ] && [ -n "$run_dir" ] && [ -d "$run_dir" ]; then
    owner=$(stat -c %u:%g "$run_dir")
    if [ "$owner" != 0:0 ]; then
        exec setpriv --reuid "${owner%:*}" --regid "${owner#*:}" --clear-groups "$0" "$@"
    fi
fi
if [ "${1:-}" = --start-run ]; then
    shift
    python -m swarmmap.services.claim start
    touch "$started"
fi
exec swarmmap "$@"
