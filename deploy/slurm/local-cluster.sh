#!/usr/bin/env bash
# A SLURM cluster of N nodes on this one machine, to try the job scripts across nodes without a
# cluster (root; Debian's slurm-wlm and munge, installed when missing).
#
#   deploy/slurm/local-cluster.sh 3       # nodes swarm-node[1-3], partition "debug"; then e.g.
#   sbatch --wait --nodes 3 --ntasks 10 deploy/slurm/team.sbatch --preset smoke --robots 3
#   deploy/slurm/local-cluster.sh stop    # stops its daemons and takes its /etc/hosts line out
#
# Each node is a slurmd of its own (Slurm's multiple-slurmd mode, `slurmd -N NAME`: its own port,
# spool folder and log, /var/log/slurm/slurmd-NAME.log); slurmctld runs beside them. The nodes
# share this host's network: their names resolve to 127.0.0.1 through a line of /etc/hosts marked
# "swarmmap local-cluster", so a job's tasks find each other by node name as on a real cluster.
# Every node claims SWARMMAP_NODE_CPUS CPUs (default 16) whatever the machine has, so that jobs of
# more tasks than cores schedule. Running it again with another N replaces the cluster; it stops
# any slurmctld and slurmd already running (a one-node cluster included) and writes
# /etc/slurm/slurm.conf; its controller keeps its state apart (/var/spool/slurmctld-swarmlocal),
# so that another cluster's controller starts again on its own state afterwards.
set -euo pipefail
[[ $(id -u) == 0 ]] || { echo "local-cluster.sh: run it as root (it starts slurmctld and slurmd)" >&2; exit 2; }
marker="# swarmmap local-cluster"
stop_daemons() {
    pkill -x slurmd 2>/dev/null || true
    pkill -x slurmctld 2>/dev/null || true
    for _ in $(seq 50); do pgrep -x slurmd >/dev/null || pgrep -x slurmctld >/dev/null || return 0; sleep 0.2; done
    pkill -9 -x slurmd 2>/dev/null || true
    pkill -9 -x slurmctld 2>/dev/null || true
}
if [[ ${1:-} == stop ]]; then
    stop_daemons
    sed -i "/$marker\$/d" /etc/hosts
    echo "local cluster stopped"
    exit 0
fi
n=${1:-3}
[[ $n =~ ^[1-9][0-9]?$ ]] || { echo "local-cluster.sh: N is a number of nodes from 1 to 99, not '$n'" >&2; exit 2; }
if ! command -v slurmctld >/dev/null; then
    apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq slurm-wlm munge >/dev/null
fi
mkdir -p /etc/slurm /var/spool/slurmctld-swarmlocal /var/log/slurm /run/munge
if [[ ! -s /etc/munge/munge.key ]]; then
    mungekey --create --force 2>/dev/null || dd if=/dev/urandom of=/etc/munge/munge.key bs=1024 count=1 2>/dev/null
fi
chown -R munge:munge /etc/munge /run/munge 2>/dev/null || true
chmod 400 /etc/munge/munge.key
pgrep -x munged >/dev/null || runuser -u munge -- munged
stop_daemons
nodes=$(printf 'swarm-node%d ' $(seq "$n"))
sed -i "/$marker\$/d" /etc/hosts
echo "127.0.0.1 ${nodes}$marker" >> /etc/hosts
host=$(hostname -s)
cpus=${SWARMMAP_NODE_CPUS:-16}
mem=$(( ($(awk '/MemTotal/ {print $2}' /proc/meminfo) / 1024 - 1024) / n ))
for i in $(seq "$n"); do mkdir -p "/var/spool/slurmd/swarm-node$i"; done
range="swarm-node[1-$n]"; ports="[17001-$((17000 + n))]"
(( n == 1 )) && { range=swarm-node1; ports=17001; }
cat > /etc/slurm/slurm.conf <<CONF
ClusterName=swarmlocal
SlurmctldHost=${host}
SlurmUser=root
SlurmdUser=root
AuthType=auth/munge
StateSaveLocation=/var/spool/slurmctld-swarmlocal
SlurmdSpoolDir=/var/spool/slurmd/%n
SlurmdPidFile=/run/slurmd-%n.pid
SlurmdLogFile=/var/log/slurm/slurmd-%n.log
SlurmctldLogFile=/var/log/slurm/slurmctld.log
ProctrackType=proctrack/linuxproc
TaskPlugin=task/none
SchedulerType=sched/backfill
SelectType=select/cons_tres
SelectTypeParameters=CR_Core
ReturnToService=2
MpiDefault=none
SlurmdParameters=config_overrides
NodeName=${range} NodeHostname=${host} NodeAddr=127.0.0.1 Port=${ports} CPUs=${cpus} RealMemory=${mem} State=UNKNOWN
PartitionName=debug Nodes=${range} Default=YES MaxTime=INFINITE State=UP OverSubscribe=FORCE:16
CONF
slurmctld
for i in $(seq "$n"); do slurmd -N "swarm-node$i"; done
for _ in $(seq 60); do
    up=$(sinfo -h -N -o '%N %T' 2>/dev/null | grep -cE ' (idle|mix|alloc)' || true)
    (( up >= n )) && break
    sleep 1
done
sinfo -N
(( up >= n )) || { echo "local-cluster.sh: $up of $n nodes came up; see /var/log/slurm/" >&2; exit 1; }
