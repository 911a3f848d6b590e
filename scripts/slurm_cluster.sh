#!/usr/bin/env bash
# A one-node SLURM cluster on this machine, for testing the workflow's SLURM profile (make test-slurm).
#
#   scripts/slurm_cluster.sh up       install slurm-wlm + munge with apt when missing, write the config, start
#                                     munged, slurmctld and slurmd (nothing is done when they already run)
#   scripts/slurm_cluster.sh down     cancel every job, stop the three daemons; nothing is left running
#   scripts/slurm_cluster.sh status   which daemons run, the node as sinfo sees it
#   scripts/slurm_cluster.sh env      the line to eval so that sbatch/squeue/sinfo talk to this cluster:
#                                     eval "$(scripts/slurm_cluster.sh env)"
#
# Everything (slurm.conf, munge key, spool and state folders, logs, pid files) lives under
# $RTSPLAT_SLURM_STATE (default /tmp/rtsplat-slurm); nothing is written to /etc or the repository. Two
# runtime paths are outside it, as on any SLURM node: munged's socket /run/munge/munge.socket.2 and
# slurmd's link /run/slurm/conf to the config it fetched from slurmctld (configless mode), which is where
# sbatch, squeue and srun find the cluster, also inside jobs (the executor plugin's job step drops
# SLURM_CONF from the environment); `down` removes both. The node is this machine with its real CPU count and memory
# (slurmd -C), no GPU, one partition "cpu". Process tracking by process tree (proctrack/linuxproc,
# task/none): no cgroups needed. No accounting database: the Snakemake SLURM executor plugin queries job
# states with squeue (profiles/slurm: slurm-status-command squeue), which works while slurmctld keeps
# finished jobs (MinJobAge, 600 s here); the completion record of every job goes to jobcomp.log
# (jobcomp/filetxt), which is what make test-slurm reads to check that each rule ran as a SLURM job.
# Needs root: slurmd starts jobs as the submitting user and munged signs the credentials.
set -euo pipefail

STATE=${RTSPLAT_SLURM_STATE:-/tmp/rtsplat-slurm}
CTLD_PORT=${RTSPLAT_SLURM_CTLD_PORT:-6817}
SLURMD_PORT=${RTSPLAT_SLURM_SLURMD_PORT:-6818}
CONF=$STATE/slurm.conf
# munged's default socket: slurmd in configless mode talks to it before it has the config naming another
MUNGE_SOCKET=/run/munge/munge.socket.2
NODE=$(hostname -s)

say() { echo "slurm_cluster: $*" >&2; }
die() { say "error: $*"; exit 1; }

need_root() {
    [ "$(id -u)" -eq 0 ] || die "must run as root (slurmd starts jobs as their user, munged signs credentials); run: sudo $0 $1"
}

missing_packages() {
    local missing=()
    command -v munged >/dev/null 2>&1 || missing+=(munge)
    for tool in slurmctld slurmd sbatch squeue scancel sinfo; do
        command -v "$tool" >/dev/null 2>&1 || { missing+=(slurm-wlm); break; }
    done
    echo "${missing[@]:-}"
}

install_packages() {
    local missing
    missing=$(missing_packages)
    [ -z "$missing" ] && return 0
    command -v apt-get >/dev/null 2>&1 || die "missing packages ($missing) and no apt-get to install them; install slurm-wlm and munge"
    say "installing $missing with apt-get"
    if ! DEBIAN_FRONTEND=noninteractive apt-get install -y --no-install-recommends $missing >"$STATE/apt.log" 2>&1; then
        tail -n 5 "$STATE/apt.log" >&2
        die "apt-get install $missing failed (log: $STATE/apt.log); install slurm-wlm and munge by hand"
    fi
    missing=$(missing_packages)
    [ -z "$missing" ] || die "still missing after apt-get install: $missing"
}

pid_alive() { [ -f "$1" ] && kill -0 "$(cat "$1")" 2>/dev/null; }

running() {  # all three daemons alive and slurmctld answering
    pid_alive "$STATE/munged.pid" && pid_alive "$STATE/slurmctld.pid" && pid_alive "$STATE/slurmd.pid" \
        && SLURM_CONF=$CONF scontrol ping 2>/dev/null | grep -q "is UP"
}

write_config() {
    local node_line
    # the node as slurmd sees this machine: CPUs, sockets, cores, threads and RealMemory (MB)
    node_line=$(slurmd -C | head -n 1 | sed "s/^NodeName=[^ ]*/NodeName=$NODE/")
    mkdir -p "$STATE/ctld" "$STATE/spool" "$STATE/munge"
    cat >"$CONF" <<EOF
# written by scripts/slurm_cluster.sh: a one-node test cluster
ClusterName=rtsplat
SlurmctldHost=$NODE(127.0.0.1)
SlurmctldPort=$CTLD_PORT
SlurmdPort=$SLURMD_PORT
SlurmUser=root
SlurmdUser=root
AuthType=auth/munge
AuthInfo=socket=$MUNGE_SOCKET
CredType=cred/munge
StateSaveLocation=$STATE/ctld
SlurmdSpoolDir=$STATE/spool
SlurmctldPidFile=$STATE/slurmctld.pid
SlurmdPidFile=$STATE/slurmd.pid
SlurmctldLogFile=$STATE/slurmctld.log
SlurmdLogFile=$STATE/slurmd.log
ProctrackType=proctrack/linuxproc
TaskPlugin=task/none
JobAcctGatherType=jobacct_gather/none
AccountingStorageType=accounting_storage/none
JobCompType=jobcomp/filetxt
JobCompLoc=$STATE/jobcomp.log
SchedulerType=sched/backfill
SelectType=select/cons_tres
SelectTypeParameters=CR_CPU_Memory
DefMemPerCPU=512
MinJobAge=600
KillWait=30
ReturnToService=2
MpiDefault=none
SlurmctldParameters=enable_configless
SlurmctldTimeout=30
SlurmdTimeout=60
$node_line NodeAddr=127.0.0.1 State=UNKNOWN
PartitionName=cpu Nodes=$NODE Default=YES MaxTime=INFINITE State=UP
EOF
}

start_munge() {
    pid_alive "$STATE/munged.pid" && return 0
    if [ ! -s "$STATE/munge/munge.key" ]; then
        dd if=/dev/urandom of="$STATE/munge/munge.key" bs=1024 count=1 status=none
    fi
    chmod 700 "$STATE/munge"
    chmod 400 "$STATE/munge/munge.key"
    if [ -S "$MUNGE_SOCKET" ] && munge -n -S "$MUNGE_SOCKET" >/dev/null 2>&1; then
        die "another munged already serves $MUNGE_SOCKET (a system one?); stop it, or use that cluster"
    fi
    mkdir -p "$(dirname "$MUNGE_SOCKET")"
    munged --force --key-file="$STATE/munge/munge.key" --socket="$MUNGE_SOCKET" \
        --pid-file="$STATE/munged.pid" --log-file="$STATE/munged.log" --seed-file="$STATE/munge/munge.seed"
}

wait_for() {  # wait_for <seconds> <what> <command...>
    local seconds=$1 what=$2
    shift 2
    for _ in $(seq $((seconds * 5))); do
        "$@" >/dev/null 2>&1 && return 0
        sleep 0.2
    done
    die "$what did not come up within ${seconds}s (logs in $STATE)"
}

node_idle() { SLURM_CONF=$CONF sinfo -h -N -o %T | grep -qE "^(idle|mixed|allocated)"; }

up() {
    need_root up
    mkdir -p "$STATE"
    install_packages
    if running; then
        say "already running (SLURM_CONF=$CONF)"
        return 0
    fi
    stop_daemons  # whatever part of an earlier cluster is left
    write_config
    start_munge
    wait_for 10 munged test -S "$MUNGE_SOCKET"
    # -c: a fresh controller, no jobs recovered from an earlier cluster in this state folder
    slurmctld -c -f "$CONF"
    wait_for 30 slurmctld sh -c "SLURM_CONF='$CONF' scontrol ping | grep -q 'is UP'"
    # configless: slurmd fetches the config from slurmctld and links it to /run/slurm/conf, where the client
    # commands inside a job find it (the executor plugin's job step drops SLURM_CONF from their environment)
    slurmd --conf-server "127.0.0.1:$CTLD_PORT" -N "$NODE"
    wait_for 60 "slurmd (node $NODE)" node_idle
    say "up: node $(SLURM_CONF=$CONF sinfo -h -N -o '%N %c CPUs %m MB %G gres %T'); SLURM_CONF=$CONF"
}

stop_pid() {  # stop_pid <pid file> <name>
    local file=$1 name=$2 pid
    pid_alive "$file" || { rm -f "$file"; return 0; }
    pid=$(cat "$file")
    kill -TERM "$pid" 2>/dev/null || true
    for _ in $(seq 100); do
        kill -0 "$pid" 2>/dev/null || { rm -f "$file"; return 0; }
        sleep 0.1
    done
    say "$name ($pid) ignored SIGTERM for 10 s; killing it"
    kill -KILL "$pid" 2>/dev/null || true
    rm -f "$file"
}

stop_daemons() {
    stop_pid "$STATE/slurmd.pid" slurmd
    stop_pid "$STATE/slurmctld.pid" slurmctld
    stop_pid "$STATE/munged.pid" munged
    # the link slurmd made to its copy of the config, when it points into this state folder
    if [ -L /run/slurm/conf ] && [[ "$(readlink /run/slurm/conf)" == "$STATE"/* ]]; then
        rm -f /run/slurm/conf
    fi
}

down() {
    need_root down
    [ -d "$STATE" ] || { say "not running (no $STATE)"; return 0; }
    if pid_alive "$STATE/slurmctld.pid" && pid_alive "$STATE/slurmd.pid"; then
        # the jobs' processes (slurmstepd and below) outlive slurmd: end them through SLURM first
        SLURM_CONF=$CONF scancel --full --signal=KILL --state=RUNNING 2>/dev/null || true
        SLURM_CONF=$CONF scancel 2>/dev/null || true
        for _ in $(seq 150); do
            [ -z "$(SLURM_CONF=$CONF squeue -h -t RUNNING,COMPLETING,PENDING -o %i 2>/dev/null)" ] && break
            sleep 0.2
        done
    fi
    stop_daemons
    say "down (state and logs kept in $STATE)"
}

status() {
    local name
    for name in munged slurmctld slurmd; do
        if pid_alive "$STATE/$name.pid"; then echo "$name: running (pid $(cat "$STATE/$name.pid"))"; else echo "$name: stopped"; fi
    done
    if running; then
        SLURM_CONF=$CONF sinfo -N -o "%N %P %c %m %G %T"
        return 0
    fi
    return 1
}

case "${1:-}" in
    up) up ;;
    down) down ;;
    status) status ;;
    env) echo "export SLURM_CONF=$CONF" ;;
    *) echo "usage: $0 up|down|status|env" >&2; exit 2 ;;
esac
