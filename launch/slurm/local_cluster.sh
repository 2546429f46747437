#!/usr/bin/env bash
# A one-node Slurm cluster on this machine (slurmctld and slurmd on localhost, munge for auth), to
# try launch/slurm/train.sbatch or run tests/test_slurm.py. Debian/Ubuntu, as root:
#
#   apt-get install -y slurm-wlm munge
#   launch/slurm/local_cluster.sh start      # writes /etc/slurm/slurm.conf, starts the daemons
#   sinfo                                    # partition "debug", one node, state idle
#   launch/slurm/local_cluster.sh stop
#
# The node offers every CPU of the machine; the "debug" partition oversubscribes them, so jobs
# with more tasks than cores still start (each task is one JAX process).
set -euo pipefail

cmd=${1:-start}
host=$(hostname -s)
conf=/etc/slurm/slurm.conf

stop() {
  scontrol shutdown >/dev/null 2>&1 || true
  for pidfile in /run/slurmd.pid /run/slurmctld.pid /run/munge/munged.pid; do
    if [ -f "$pidfile" ]; then kill "$(cat "$pidfile")" 2>/dev/null || true; fi
  done
}

if [ "$cmd" = stop ]; then
  stop
  exit 0
fi
if [ "$cmd" != start ]; then
  echo "usage: $0 start|stop" >&2
  exit 2
fi

stop
sleep 1
mkdir -p /etc/slurm /var/spool/slurmctld /var/spool/slurmd /var/log/slurm /run/munge
chown slurm: /var/spool/slurmctld /var/log/slurm
chown munge: /run/munge
if [ ! -s /etc/munge/munge.key ]; then
  mungekey --create --keyfile=/etc/munge/munge.key
  chown munge: /etc/munge/munge.key
  chmod 400 /etc/munge/munge.key
fi
mem_mb=$(awk '/MemTotal/ {print int($2 / 1024 * 0.9)}' /proc/meminfo)
cat > "$conf" <<CONF
# One-node cluster written by launch/slurm/local_cluster.sh
ClusterName=local
SlurmctldHost=$host
AuthType=auth/munge
CredType=cred/munge
# A requeued job waits cred_expire seconds (default 120) before it may start again; a local
# cluster needs no more than a few seconds for a step's credential.
AuthInfo=cred_expire=10
SlurmUser=slurm
SlurmctldPidFile=/run/slurmctld.pid
SlurmdPidFile=/run/slurmd.pid
StateSaveLocation=/var/spool/slurmctld
SlurmdSpoolDir=/var/spool/slurmd
SlurmctldLogFile=/var/log/slurm/slurmctld.log
SlurmdLogFile=/var/log/slurm/slurmd.log
# No cgroups in a container: track processes by parent, bind nothing.
ProctrackType=proctrack/linuxproc
TaskPlugin=task/none
JobAcctGatherType=jobacct_gather/none
SelectType=select/cons_tres
SelectTypeParameters=CR_Core
SchedulerType=sched/backfill
# A requeued job becomes eligible again with no event to wake the scheduler: it waits for the next
# periodic pass (backfill every 30 s and the main loop every 60 by default). One node, few jobs:
# a pass every 2 s costs nothing here.
SchedulerParameters=bf_interval=2,sched_interval=2
MpiDefault=none
ReturnToService=2
JobRequeue=1
# Seconds between SIGTERM and SIGKILL when a job is cancelled, preempted or out of time.
KillWait=120
SlurmdParameters=config_overrides
NodeName=$host CPUs=$(nproc) RealMemory=$mem_mb State=UNKNOWN
PartitionName=debug Nodes=$host Default=YES MaxTime=INFINITE State=UP OverSubscribe=FORCE:4
CONF
runuser -u munge -- munged
slurmctld
slurmd
for _ in $(seq 30); do
  if sinfo -h -o %t 2>/dev/null | grep -q idle; then
    sinfo
    exit 0
  fi
  sleep 1
done
echo "slurm did not come up: see /var/log/slurm/slurmctld.log and slurmd.log" >&2
exit 1
