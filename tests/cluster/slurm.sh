#!/usr/bin/env bash
# A two-node SLURM cluster on this machine, for `make test-cluster` (docs/cluster.md):
#   tests/cluster/slurm.sh start   install what is missing from Debian's packages (slurmctld, slurmd,
#                                  slurm-client, munge, slurmdbd, mariadb-server), write a private
#                                  configuration under $STATE, start munged, MariaDB, slurmdbd, slurmctld
#                                  and two slurmd (nodes n1 and n2, each half of the machine's cores,
#                                  one port each: slurmd -N) by hand (no systemd) and wait until a job
#                                  runs on each
#   tests/cluster/slurm.sh stop    stop every daemon it started, by the process ids it recorded
#   tests/cluster/slurm.sh install only install what is missing (.ci/run does it while the tests run)
# Clients find the cluster through SLURM_CONF=$STATE/slurm.conf (printed by `start`). Exits 3 with one
# line where it cannot run (not root, not Debian, no apt); nothing outside $STATE, /run/munge,
# /run/mysqld and the database is changed.
set -euo pipefail
STATE=${PHYSGRAD_SLURM_STATE:-/tmp/physgrad-slurm}
CLUSTER=physgrad
PARTITION=debug
PACKAGES="slurmctld slurmd slurm-client munge slurmdbd mariadb-server mariadb-client"

cannot() { echo "test-cluster: cannot run here: $*" >&2; exit 3; }
say() { echo "test-cluster: $*"; }

wait_for() { # seconds, what, command...
    local seconds=$1 what=$2; shift 2
    for _ in $(seq 1 $((seconds * 4))); do
        if "$@" >/dev/null 2>&1; then return 0; fi
        sleep 0.25
    done
    echo "test-cluster: $what did not come up within ${seconds} s (logs: $STATE/log)" >&2
    tail -n 20 "$STATE"/log/* >&2 || true
    return 1
}

start_daemon() { # name, pid file, command...: started in the background, its pid recorded
    local name=$1 pidfile=$2; shift 2
    "$@" >>"$STATE/log/$name.out" 2>&1 &
    echo $! >"$pidfile"
}

install_missing() {
    local missing=()
    for package in $PACKAGES; do
        dpkg-query -W -f='${Status}' "$package" 2>/dev/null | grep -q "install ok installed" \
            || missing+=("$package")
    done
    [ ${#missing[@]} -eq 0 ] && return 0
    command -v apt-get >/dev/null || cannot "no apt-get to install ${missing[*]}"
    say "installing ${missing[*]} from Debian's packages"
    # services are never started by the packages here (no systemd; policy-rc.d may refuse)
    DEBIAN_FRONTEND=noninteractive apt-get update -qq
    DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends "${missing[@]}" \
        >"$STATE/log/apt.out" 2>&1 || { tail -n 20 "$STATE/log/apt.out" >&2; cannot "apt-get install failed"; }
}

write_config() {
    local node cpus memory
    node=$(hostname -s)
    cpus=$(( $(nproc) / 2 > 0 ? $(nproc) / 2 : 1 ))
    memory=$(( $(slurmd -C | sed -n 's/.*RealMemory=\([0-9]*\).*/\1/p') / 2 ))
    mkdir -p "$STATE/spool/ctld" "$STATE/spool/d-n1" "$STATE/spool/d-n2" "$STATE/log" "$STATE/run"
    cat >"$STATE/slurm.conf" <<EOF
ClusterName=$CLUSTER
SlurmctldHost=$node(127.0.0.1)
SlurmUser=root
SlurmdUser=root
AuthType=auth/munge
StateSaveLocation=$STATE/spool/ctld
SlurmdSpoolDir=$STATE/spool/d-%n
SlurmctldPidFile=$STATE/run/slurmctld.pid
SlurmdPidFile=$STATE/run/slurmd-%n.pid
SlurmctldLogFile=$STATE/log/slurmctld.log
SlurmdLogFile=$STATE/log/slurmd-%n.log
SlurmctldPort=6817
SlurmdPort=6818
ProctrackType=proctrack/linuxproc
TaskPlugin=task/none
SwitchType=switch/none
MpiDefault=none
SchedulerType=sched/backfill
SelectType=select/cons_tres
SelectTypeParameters=CR_Core
ReturnToService=2
SlurmdTimeout=15
KillWait=30
MinJobAge=300
SchedulerParameters=sched_interval=2
AccountingStorageType=accounting_storage/slurmdbd
AccountingStorageHost=localhost
JobAcctGatherType=jobacct_gather/none
NodeName=n1 NodeHostname=$node NodeAddr=127.0.0.1 Port=6831 CPUs=$cpus RealMemory=$memory State=UNKNOWN
NodeName=n2 NodeHostname=$node NodeAddr=127.0.0.1 Port=6832 CPUs=$cpus RealMemory=$memory State=UNKNOWN
PartitionName=$PARTITION Nodes=n1,n2 Default=YES MaxTime=INFINITE State=UP
EOF
    cat >"$STATE/slurmdbd.conf" <<EOF
AuthType=auth/munge
DbdHost=localhost
SlurmUser=root
PidFile=$STATE/run/slurmdbd.pid
LogFile=$STATE/log/slurmdbd.log
StorageType=accounting_storage/mysql
StorageHost=localhost
StorageUser=slurm
StoragePass=physgrad-test
StorageLoc=physgrad_slurm_acct
EOF
    chmod 600 "$STATE/slurmdbd.conf"
    touch "$STATE/cgroup.conf"
}

start() {
    [ "$(id -u)" -eq 0 ] || cannot "not root (the daemons and their packages need root)"
    [ -f /etc/debian_version ] || cannot "not a Debian machine (the recipe uses Debian's packages)"
    mkdir -p "$STATE/log" "$STATE/run"
    stop quietly
    install_missing
    write_config
    export SLURM_CONF=$STATE/slurm.conf

    # munge: its key comes with the package; its socket folder is made by systemd elsewhere
    [ -s /etc/munge/munge.key ] || { /usr/sbin/mungekey --create >/dev/null 2>&1 || /usr/sbin/create-munge-key -f; }
    chown munge: /etc/munge/munge.key && chmod 400 /etc/munge/munge.key
    mkdir -p /run/munge /var/log/munge /var/lib/munge && chown munge: /run/munge /var/log/munge /var/lib/munge
    runuser -u munge -- /usr/sbin/munged --pid-file=/run/munge/physgrad-munged.pid --force
    cp /run/munge/physgrad-munged.pid "$STATE/run/munged.pid"
    wait_for 20 munged bash -c 'munge -n | unmunge'

    # MariaDB for slurmdbd, which sacct (and so submitit) needs
    mkdir -p /run/mysqld && chown mysql: /run/mysqld
    [ -d /var/lib/mysql/mysql ] || mariadb-install-db --user=mysql --datadir=/var/lib/mysql >"$STATE/log/mariadb-install.out" 2>&1
    start_daemon mariadb "$STATE/run/mariadb.pid" /usr/sbin/mariadbd --user=mysql --skip-networking \
        --socket=/run/mysqld/mysqld.sock --pid-file=/run/mysqld/physgrad-mariadbd.pid
    wait_for 60 MariaDB mariadb --socket=/run/mysqld/mysqld.sock -e 'select 1'
    mariadb --socket=/run/mysqld/mysqld.sock -e "CREATE USER IF NOT EXISTS 'slurm'@'localhost' IDENTIFIED BY 'physgrad-test'; GRANT ALL ON physgrad_slurm_acct.* TO 'slurm'@'localhost'; FLUSH PRIVILEGES;"

    start_daemon slurmdbd "$STATE/run/slurmdbd.daemon" /usr/sbin/slurmdbd -D
    wait_for 60 slurmdbd sacctmgr -n list cluster
    sacctmgr -i add cluster "$CLUSTER" >/dev/null 2>&1 || true
    start_daemon slurmctld "$STATE/run/slurmctld.daemon" /usr/sbin/slurmctld -D -f "$STATE/slurm.conf"
    wait_for 60 slurmctld scontrol ping
    start_node n1
    start_node n2
    wait_for 60 "both nodes" bash -c "[ \$(sinfo -h -N -o %t | grep -Ec '^(idle|mix|alloc)') -eq 2 ]"
    wait_for 60 "a first job on n1" srun -p "$PARTITION" -w n1 -t 1 true
    wait_for 60 "a first job on n2" srun -p "$PARTITION" -w n2 -t 1 true
    wait_for 60 "sacct" bash -c "sacct -n -X -o State | grep -q COMPLETED"
    say "SLURM $(sinfo -V | cut -d' ' -f2) is up: partition $PARTITION, nodes n1 and n2 on $(hostname -s); export SLURM_CONF=$SLURM_CONF"
}

start_node() { # name: a slurmd of its own for node name (slurmd -N), its pid recorded
    start_daemon "slurmd-$1" "$STATE/run/slurmd-$1.daemon" /usr/sbin/slurmd -D -N "$1" -f "$STATE/slurm.conf"
}

own_steps() { # the job steps (slurmstepd) of this cluster's slurmd: started with its SLURM_CONF in
    # their environment, or holding a file of its state folder open (its log, its spool)
    local pid
    for pid in $(pgrep -x slurmstepd); do
        if tr '\0' '\n' <"/proc/$pid/environ" 2>/dev/null | grep -qxF "SLURM_CONF=$STATE/slurm.conf" \
            || find "/proc/$pid/fd" -maxdepth 1 -lname "$STATE/*" 2>/dev/null | grep -q .; then
            echo "$pid"
        fi
    done
}

stop() {
    local quiet=${1:-}
    for name in slurmd-n1 slurmd-n2 slurmd slurmctld slurmdbd mariadb munged; do
        local pidfile="$STATE/run/$name.daemon"
        [ -f "$pidfile" ] || pidfile="$STATE/run/$name.pid"
        [ -f "$pidfile" ] || continue
        local pid
        pid=$(cat "$pidfile")
        if [ -n "$pid" ] && kill -0 "$pid" 2>/dev/null; then
            kill -TERM "$pid" 2>/dev/null || true
            for _ in $(seq 1 80); do kill -0 "$pid" 2>/dev/null || break; sleep 0.25; done
            kill -KILL "$pid" 2>/dev/null || true
        fi
        rm -f "$pidfile"
    done
    # slurmd's job steps (slurmstepd) end with their jobs; any left from a killed test are ended here,
    # and only this cluster's: another cluster's steps on the same machine are not the harness's
    local step
    for step in $(own_steps); do kill -TERM "$step" 2>/dev/null || true; done
    [ -n "$quiet" ] || say "stopped"
}

install() {
    [ "$(id -u)" -eq 0 ] || cannot "not root (the daemons and their packages need root)"
    [ -f /etc/debian_version ] || cannot "not a Debian machine (the recipe uses Debian's packages)"
    mkdir -p "$STATE/log"
    install_missing
}

case "${1:-}" in
    start) start ;;
    start-node) export SLURM_CONF=$STATE/slurm.conf; start_node "$2" ;;
    stop) stop ;;
    install) install ;;
    *) echo "usage: $0 start|start-node NAME|stop|install" >&2; exit 2 ;;
esac
