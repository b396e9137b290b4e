#!/usr/bin/env bash
# A real one-node SLURM on this machine, for the `slurm` tests (make test-slurm) and for trying the pipeline's
# launcher=slurm without a cluster: installs Debian's slurm-wlm and munge (~25 s, as root), writes a one-node
# slurm.conf (this machine's CPUs and memory, no GPUs), starts munged, slurmctld and slurmd, and waits until the
# node takes jobs. Idempotent: a running SLURM is left as it is. Not for a real cluster (docs/operations.md).
#
#   sudo bash scripts/slurm_local.sh              # then: sinfo; sbatch --wrap hostname
#   sudo bash scripts/slurm_local.sh --accounting # also slurmdbd on a local MariaDB, so that sacct works (~1 min
#                                                 # more; experiments/cluster/README.md's sacct tables)
#   bash scripts/slurm_local.sh --stop            # stops the daemons again
set -euo pipefail

CONF_DIR=/etc/slurm
STATE=/var/spool/slurmctld
SPOOL=/var/spool/slurmd
LOGS=/var/log/slurm

if [[ "${1:-}" == "--stop" ]]; then
    pkill -x slurmd || true
    pkill -x slurmctld || true
    pkill -x slurmdbd || true
    pkill -x munged || true
    exit 0
fi
ACCOUNTING=0
[[ "${1:-}" == "--accounting" ]] && ACCOUNTING=1

if [[ $ACCOUNTING == 0 ]] && sinfo -h -o %T 2>/dev/null | grep -qE '^(idle|mix|alloc)'; then
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
$(if [[ $ACCOUNTING == 1 ]]; then printf 'AccountingStorageType=accounting_storage/slurmdbd\nAccountingStorageHost=%s' "$host"; else echo "AccountingStorageType=accounting_storage/none"; fi)
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

if [[ $ACCOUNTING == 1 ]]; then
    if ! command -v slurmdbd >/dev/null || ! command -v mariadbd >/dev/null; then
        DEBIAN_FRONTEND=noninteractive apt-get install -y -q slurmdbd mariadb-server >/dev/null
    fi
    mkdir -p /run/mysqld && chown mysql:mysql /run/mysqld
    pgrep -x mariadbd >/dev/null || (mysqld_safe >/dev/null 2>&1 &)
    for _ in $(seq 30); do mysqladmin ping >/dev/null 2>&1 && break; sleep 1; done
    mysql -e "CREATE DATABASE IF NOT EXISTS slurm_acct_db; CREATE USER IF NOT EXISTS 'slurm'@'localhost' IDENTIFIED BY 'drgan-local'; GRANT ALL ON slurm_acct_db.* TO 'slurm'@'localhost'; FLUSH PRIVILEGES;"
    printf '%s\n' "AuthType=auth/munge" "DbdHost=localhost" "SlurmUser=root" "LogFile=$LOGS/slurmdbd.log" \
        "PidFile=/run/slurmdbd.pid" "StorageType=accounting_storage/mysql" "StorageHost=localhost" \
        "StorageUser=slurm" "StoragePass=drgan-local" "StorageLoc=slurm_acct_db" > "$CONF_DIR/slurmdbd.conf"
    chmod 600 "$CONF_DIR/slurmdbd.conf"
    pgrep -x slurmdbd >/dev/null || slurmdbd
    for _ in $(seq 30); do sacctmgr -i list cluster >/dev/null 2>&1 && break; sleep 1; done
    sacctmgr -i add cluster drgan-local >/dev/null 2>&1 || true
    if pgrep -x slurmctld >/dev/null; then pkill -x slurmctld; sleep 2; fi  # a running one restarts with accounting
fi
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
