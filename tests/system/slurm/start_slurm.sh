#!/usr/bin/env bash
# A single-host SLURM for the system tests (`make test-slurm`): munged, slurmctld and slurmd
# on this machine, talking over the loopback address only. Idempotent: installs Debian's
# slurm-wlm and munge when missing, writes /etc/slurm/slurm.conf (only when absent or written
# by this script before), starts whichever daemon is not running and waits until the node is
# idle. Run as root (it installs packages and starts daemons). stop_slurm.sh stops them.
#
# Settings this needs in a container (see the comments in the slurm.conf below):
#   - ProctrackType=proctrack/linuxproc and TaskPlugin=task/none: no cgroup plugin, so no
#     writable cgroup hierarchy is needed;
#   - every address is 127.0.0.1 (SlurmctldHost, NodeAddr), so no daemon or job contacts
#     another address whatever the host name resolves to;
#   - no accounting database, no job accounting gather.
set -euo pipefail

SLURM_CONF=/etc/slurm/slurm.conf
MARKER="# written by cellcoadd tests/system/slurm/start_slurm.sh"
STATE=/var/lib/slurm
LOGS=/var/log/slurm
WAIT_S=${SLURM_START_WAIT_S:-60}

say() { echo "start_slurm: $*"; }
die() { echo "start_slurm: error: $*" >&2; exit 1; }

[ "$(id -u)" -eq 0 ] || die "run as root (installs packages, starts munged/slurmctld/slurmd)"

# 1. packages
missing=()
for cmd in munged slurmctld slurmd sinfo sbatch; do
    command -v "$cmd" >/dev/null 2>&1 || missing+=("$cmd")
done
if [ ${#missing[@]} -gt 0 ]; then
    say "installing slurm-wlm and munge (missing: ${missing[*]})"
    command -v apt-get >/dev/null || die "apt-get not found: install slurm-wlm and munge by hand"
    export DEBIAN_FRONTEND=noninteractive
    # the package lists may be absent in a fresh container
    if ! apt-cache policy slurm-wlm 2>/dev/null | grep -q 'Candidate: [0-9]'; then
        apt-get update -q
    fi
    # without recommends: the recommends are ~35 plugin packages (HDF5, InfluxDB, ROCm, ...)
    apt-get install -y -q --no-install-recommends slurm-wlm munge
fi

# 2. munge key (the Debian package makes one on install; a bare system may not have one)
if [ ! -s /etc/munge/munge.key ]; then
    say "creating /etc/munge/munge.key"
    mkdir -p /etc/munge
    if command -v mungekey >/dev/null 2>&1; then
        mungekey --create --keyfile=/etc/munge/munge.key --force
    else
        dd if=/dev/urandom of=/etc/munge/munge.key bs=1 count=1024 status=none
    fi
fi
chown munge:munge /etc/munge /etc/munge/munge.key
chmod 700 /etc/munge
chmod 400 /etc/munge/munge.key
install -d -o munge -g munge -m 755 /run/munge
install -d -o munge -g munge -m 700 /var/lib/munge /var/log/munge

# 3. slurm.conf
host=$(hostname -s)
cpus=$(nproc)
mem_mb=$(awk '/^MemTotal:/ {print int($2 / 1024)}' /proc/meminfo)
# what the jobs may ask for: all but 1 GB (at least 1 GB) of the machine's memory
real_mb=$(( mem_mb > 2048 ? mem_mb - 1024 : 1024 ))
conf=$(cat <<EOF
$MARKER
# A single-host test cluster: everything on 127.0.0.1.
ClusterName=cellcoadd-test
SlurmctldHost=$host(127.0.0.1)
SlurmUser=root
SlurmctldPort=6817
SlurmdPort=6818
AuthType=auth/munge
StateSaveLocation=$STATE/slurmctld
SlurmdSpoolDir=$STATE/slurmd
SlurmctldPidFile=/run/slurmctld.pid
SlurmdPidFile=/run/slurmd.pid
SlurmctldLogFile=$LOGS/slurmctld.log
SlurmdLogFile=$LOGS/slurmd.log
SlurmctldDebug=info
SlurmdDebug=info
# no cgroups: processes are tracked through /proc and their parents, tasks not bound
ProctrackType=proctrack/linuxproc
TaskPlugin=task/none
JobAcctGatherType=jobacct_gather/none
AccountingStorageType=accounting_storage/none
MpiDefault=none
# no mail from a test cluster (Debian has no /bin/mail by default)
MailProg=/bin/true
# a node found down after a restart (or seen unresponsive) is back in service when it registers
ReturnToService=2
SchedulerType=sched/backfill
SelectType=select/cons_tres
SelectTypeParameters=CR_Core_Memory
# a cancelled job's processes get 5 s between SIGTERM and SIGKILL
KillWait=5
# quick scheduling and node checks: the test's replacement job starts in seconds
SchedulerParameters=sched_interval=2
SlurmdTimeout=60
InactiveLimit=0
MinJobAge=60
NodeName=$host NodeAddr=127.0.0.1 NodeHostname=$host CPUs=$cpus RealMemory=$real_mb State=UNKNOWN
PartitionName=debug Nodes=$host Default=YES MaxTime=INFINITE State=UP
EOF
)
if [ -f "$SLURM_CONF" ] && ! grep -qF "$MARKER" "$SLURM_CONF"; then
    die "$SLURM_CONF exists and was not written by this script: not touching it"
fi
restart=0
if [ ! -f "$SLURM_CONF" ] || [ "$(cat "$SLURM_CONF")" != "$conf" ]; then
    say "writing $SLURM_CONF (node $host: $cpus CPUs, $real_mb MB)"
    mkdir -p "$(dirname "$SLURM_CONF")"
    printf '%s\n' "$conf" > "$SLURM_CONF.tmp"
    mv "$SLURM_CONF.tmp" "$SLURM_CONF"
    restart=1
fi
mkdir -p "$STATE/slurmctld" "$STATE/slurmd" "$LOGS"

# a daemon is running when its pid file names a live process of that name
running() {  # name pidfile
    local pid
    [ -f "$2" ] || return 1
    pid=$(cat "$2" 2>/dev/null) || return 1
    [ -n "$pid" ] && [ "$(cat /proc/"$pid"/comm 2>/dev/null)" = "$1" ]
}

# 4. daemons
if ! running munged /run/munge/munged.pid; then
    say "starting munged"
    runuser -u munge -- /usr/sbin/munged
fi
for _ in $(seq 50); do
    munge -n 2>/dev/null | unmunge >/dev/null 2>&1 && break
    sleep 0.2
done
munge -n | unmunge >/dev/null || die "munge does not work (see /var/log/munge/munged.log)"

if [ "$restart" = 1 ]; then
    # a new configuration: daemons started with the old one are restarted
    for pair in slurmd:/run/slurmd.pid slurmctld:/run/slurmctld.pid; do
        name=${pair%%:*}; pidfile=${pair#*:}
        if running "$name" "$pidfile"; then
            say "stopping $name (new configuration)"
            kill "$(cat "$pidfile")"
            for _ in $(seq 50); do running "$name" "$pidfile" || break; sleep 0.2; done
        fi
    done
fi
if ! running slurmctld /run/slurmctld.pid; then
    # -c: a fresh controller without the jobs of an earlier start (a test cluster)
    say "starting slurmctld"
    /usr/sbin/slurmctld -c
fi
if ! running slurmd /run/slurmd.pid; then
    say "starting slurmd"
    /usr/sbin/slurmd
fi

# 5. wait (bounded) until the node takes jobs
deadline=$(( $(date +%s) + WAIT_S ))
while :; do
    state=$(sinfo -h -N -n "$host" -o '%T' 2>/dev/null | head -1 || true)
    case "$state" in
        idle|mixed|allocated) say "node $host is $state"; break ;;
        down*|drain*|fail*)
            # e.g. "down" after an unclean restart: the node is up now, put it back
            scontrol update NodeName="$host" State=RESUME >/dev/null 2>&1 || true ;;
    esac
    if [ "$(date +%s)" -ge "$deadline" ]; then
        sinfo -N -l >&2 || true
        tail -n 20 "$LOGS/slurmctld.log" "$LOGS/slurmd.log" >&2 || true
        die "node $host not idle after ${WAIT_S} s (state: '${state:-no answer}'); logs in $LOGS"
    fi
    sleep 1
done
