#!/usr/bin/env bash
# Stops the single-host SLURM that start_slurm.sh started (slurmd, slurmctld, munged), each
# by the process id in its pid file; the packages and /etc/slurm/slurm.conf stay.
set -euo pipefail

stop() {  # name pidfile
    local pid
    [ -f "$2" ] || return 0
    pid=$(cat "$2" 2>/dev/null) || return 0
    if [ -n "$pid" ] && [ "$(cat /proc/"$pid"/comm 2>/dev/null)" = "$1" ]; then
        echo "stop_slurm: stopping $1 ($pid)"
        kill "$pid"
        for _ in $(seq 50); do
            [ "$(cat /proc/"$pid"/comm 2>/dev/null)" = "$1" ] || return 0
            sleep 0.2
        done
        echo "stop_slurm: $1 ($pid) still running after 10 s" >&2
        return 1
    fi
}

stop slurmd /run/slurmd.pid
stop slurmctld /run/slurmctld.pid
stop munged /run/munge/munged.pid
