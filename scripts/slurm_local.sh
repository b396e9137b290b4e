#!/usr/bin/env bash
# A real one-node SLURM on this machine, for the `slurm` tests (make test-slurm) and for trying the pipeline's
# launcher=slurm without a cluster: installs Debian's slurm-wlm and munge (~25 s, as root), writes a one-node
# slurm.conf (this machine's CPUs and memory, no GPUs), starts munged, slurmctld and slurmd, and waits until the
# node takes jobs. Idempotent: a running SLURM is left as it is. Not for a real cluster (docs/operations.md).
#
#   sudo bash scripts/slurm_local.sh          # then: sinfo; sbatch --wrap hostname
#   bash scripts/slurm_local.sh --stop        # stops the three daemons again
set -euo pipefail

CONF_DIR=/etc/slurm
STATE=/var/spool/slurmctld
SPOOL=/var/spool/slurmd
LOGS=/var/log/slurm

if [[ "${1:-}" == "--stop" ]]; then
    pkill -x slurmd || true
    pkill -x slurmctld || true
    pkill -x munged || true
    exit 0
fi

if sinfo -h -o %T 2>/dev/null | grep -qE '^(idle|mix|alloc)'; then
    echo "slurm_local: a SLURM is running here already: $(sinfo -h -o '%P %D %T' | head -1)"
    exit 0
fi
if [[ $(id -u) -ne 0 ]]; then
    echo "slurm_local: needs root (apt-get, the daemons); run it with sudo" >&2
    exit 1
fi
if ! command -v slurmctld >/dev/null || ! command -v munged >/dev/null; then
    DEBIAN_FRONTEND=noninteractive apt-get install -y -q slurm-wlm munge >/dev/null
fi

host=$(hostname -s)
cpus=$(nproc)
# slurmd's own reading of the memory (MiB), less a margin, so that the node is never drained for "low memory"
mem=$(( $(awk '/MemTotal/ {print int($2 / 1024)}' /proc/meminfo) * 9 / 10 ))
mkdir -p "$CONF_DIR" "$STATE" "$SPOOL" "$LOGS"
cat > "$CONF_DIR/slurm.conf" <<EOF
# written by drgan's scripts/slurm_local.sh: one node, this machine
ClusterName=drgan-local
SlurmctldHost=$host
SlurmUser=root
SlurmdUser=root
AuthType=auth/munge
StateSaveLocation=$STATE
SlurmdSpoolDir=$SPOOL
SlurmctldLogFile=$LOGS/slurmctld.log
SlurmdLogFile=$LOGS/slurmd.log
SlurmctldPidFile=/run/slurmctld.pid
SlurmdPidFile=/run/slurmd.pid
SelectType=select/cons_tres
SelectTypeParameters=CR_Core_Memory
ProctrackType=proctrack/linuxproc
TaskPlugin=task/none
JobAcctGatherType=jobacct_gather/none
JobCompType=jobcomp/none
AccountingStorageType=accounting_storage/none
ReturnToService=2
SchedulerType=sched/backfill
MinJobAge=3600
KillWait=10
NodeName=$host CPUs=$cpus RealMemory=$mem State=UNKNOWN
PartitionName=main Nodes=$host Default=YES MaxTime=INFINITE State=UP
EOF

if [[ ! -s /etc/munge/munge.key ]]; then
    mkdir -p /etc/munge
    dd if=/dev/urandom bs=1 count=1024 of=/etc/munge/munge.key status=none
fi
chown -R munge:munge /etc/munge 2>/dev/null || true
chmod 400 /etc/munge/munge.key
mkdir -p /run/munge /var/lib/munge /var/log/munge
chown munge:munge /run/munge /var/lib/munge /var/log/munge 2>/dev/null || true
pgrep -x munged >/dev/null || su -s /bin/sh munge -c munged 2>/dev/null || munged --force
pgrep -x slurmctld >/dev/null || slurmctld
pgrep -x slurmd >/dev/null || slurmd

for _ in $(seq 60); do
    if sinfo -h -o %T 2>/dev/null | grep -qE '^(idle|mix|alloc)'; then
        echo "slurm_local: SLURM up: partition main, node $host, $cpus CPUs, ${mem} MiB"
        exit 0
    fi
    sleep 1
done
echo "slurm_local: SLURM did not come up in 60 s; its logs: $LOGS/slurmctld.log, $LOGS/slurmd.log" >&2
sinfo >&2 || true
exit 1
