#!/bin/sh
# The entrypoint of every swarmmap container: `swarmmap ARGS`, as the owner of the run directory.
#
#   swarmmap-entrypoint ARGS              swarmmap ARGS
#   swarmmap-entrypoint --start-run       the start of the run, then its signer (compose's start container)
#
# Started as root (compose's default user) with SWARMMAP_RUN_DIR set, it runs swarmmap as the
# owner of that directory, so that a run's files belong to whoever owns the run, not to root
# (rootless engines map root to the invoking user already; compose's `user:` skips all this).
#
# The start of a run (compose's first step; the other services wait for it) gives the runs
# folder and the run directory, when the engine has just made them (root's and empty), to the
# owner of /etc/swarmmap/compose.yaml (compose mounts its file there: the user who cloned the
# repository), then, as the run directory's owner, runs `python -m swarmmap.services.up.claim start`:
# it refuses a run directory holding a finished run, or one that did not finish unless
# SWARMMAP_UP__RESUME=true resumes it (the same settings only), writes config.yaml, makes the
# run's CA (its key in that process's memory only), forgets the robot claims of an earlier `up`,
# writes its verdict to $SWARMMAP_START/start (a folder the services mount read-only; without
# SWARMMAP_START, $SWARMMAP_ROBOT_CLAIMS), then signs each service's certificate until the run is over. Every other service of a compose run (SWARMMAP_ROBOT_CLAIMS set) reads that
# verdict first and stops, naming it, unless it is `ok` (compose v1 starts the others even when
# the start container has exited); it then makes its own key in its own file system and asks the
# signer for the certificate of the identity it serves (zenoh.signer).
set -eu
run_dir=${SWARMMAP_RUN_DIR:-}
shared=${SWARMMAP_START:-${SWARMMAP_ROBOT_CLAIMS:-}}  # the start's verdict and the services' lock (read-only to them)

adopt() {  # adopt DIR OWNER: give DIR to OWNER when the engine made it for a bind mount
    if [ -d "$1" ] && [ "$(stat -c %u:%g "$1")" = 0:0 ] && [ -z "$(ls -A "$1")" ]; then chown "$2" "$1"; fi
}

as_owner() {  # as_owner UID:GID COMMAND...: run COMMAND as that user and group
    who=$1; shift
    setpriv --reuid "${who%:*}" --regid "${who#*:}" --clear-groups "$@"
}

if [ "${1:-}" = --start-run ] && [ -n "$shared" ]; then
    rm -f "$shared/start"  # an earlier run's verdict is not this one's
fi
if [ "${1:-}" = --start-run ] && [ "$(id -u)" = 0 ]; then
    if [ -n "$run_dir" ] && [ -e /etc/swarmmap/compose.yaml ]; then
        owner=$(stat -c %u:%g /etc/swarmmap/compose.yaml)
        adopt "$(dirname "$run_dir")" "$owner"
        [ -e "$run_dir" ] || as_owner "$owner" mkdir -p "$run_dir" || mkdir -p "$run_dir"
        adopt "$run_dir" "$owner"
    fi
fi
if [ "$(id -u)" = 0 ] && [ -n "$run_dir" ] && [ -d "$run_dir" ] && [ "$(stat -c %u:%g "$run_dir")" != 0:0 ]; then
    exec setpriv --reuid "$(stat -c %u "$run_dir")" --regid "$(stat -c %g "$run_dir")" --clear-groups "$0" "$@"
fi
if [ "${1:-}" = --start-run ]; then
    exec python -m swarmmap.services.up.claim start
elif [ -n "$shared" ]; then
    case "${1:-}" in
    router | recorder | world | lidar | learner | observer)  # a service of the run; other commands are not held back
        verdict=$(cat "$shared/start" 2>/dev/null || true)
        if [ "$verdict" != ok ]; then
            echo "this run did not start (${shared}/start): ${verdict:-the start container has not started it}" >&2
            exit 2
        fi
        # A shared lock held for as long as the service runs: the start container ends once none is
        # held (the start made the file; reading it is enough to lock it).
        if [ -r "$shared/running" ]; then
            exec 9<"$shared/running"
            flock -s 9
        fi
        ;;
    esac
fi
exec swarmmap "$@"
