#!/usr/bin/env bash
# Start a one-node SLURM cluster on this machine for the cluster tests (tests/cluster/), and hand over its config:
#
#   export SLURM_CONF="$(bash .ci/slurm.sh)"   # run: prints the path of slurm.conf on stdout
#   . .ci/slurm.sh                             # sourced: exports SLURM_CONF itself
#
# Installs Debian's slurm-wlm and munge when they are missing (as root), writes a slurm.conf of its own in
# $SB3_TD3X_SLURM_DIR (default /var/tmp/sb3-td3x-slurm): one node (this machine, with 90% of its memory and at least
# 4 CPUs: two jobs of sweeps/launcher/slurm.yaml's 2 CPUs side by side even on a 2-core machine), one partition
# `debug`, no accounting (as on many small clusters), jobs requeueable, then starts munged, slurmctld and slurmd and
# waits until the node is idle. Idempotent: a second call finds the daemons running and prints the
# same path. A machine that already has a SLURM of its own (/etc/slurm/slurm.conf) is left alone: its conf is
# printed and nothing is started.
# Everything runs in a subshell, so that sourcing this file leaves the caller's shell as it was.
_sb3_td3x_start_slurm() (
  set -euo pipefail
  DIR="${SB3_TD3X_SLURM_DIR:-/var/tmp/sb3-td3x-slurm}"
  CONF="$DIR/slurm.conf"
  log() { echo "[slurm.sh] $*" >&2; }

  if [ -f /etc/slurm/slurm.conf ] && [ "${SB3_TD3X_SLURM_DIR:-}" = "" ] && ! grep -q "sb3-td3x" /etc/slurm/slurm.conf; then
    log "this machine has a SLURM of its own: using /etc/slurm/slurm.conf"
    echo /etc/slurm/slurm.conf
    exit 0
  fi
  if ! command -v slurmctld >/dev/null || ! command -v munged >/dev/null; then
    if [ "$(id -u)" -ne 0 ]; then
      log "SLURM is not installed and this is not root: install Debian's slurm-wlm and munge first"
      exit 1
    fi
    log "installing slurm-wlm and munge from Debian's packages"
    export DEBIAN_FRONTEND=noninteractive
    apt-get update -qq >&2
    apt-get install -y -qq slurm-wlm munge >&2
  fi
  if [ "$(id -u)" -ne 0 ]; then
    log "starting slurmd needs root (it runs jobs as their users)"
    exit 1
  fi
  export SLURM_CONF="$CONF"

  # munge: the key the package made, a socket folder of its own
  if [ ! -s /etc/munge/munge.key ]; then
    log "creating a munge key"
    mungekey --create --keyfile /etc/munge/munge.key >&2 2>/dev/null || dd if=/dev/urandom of=/etc/munge/munge.key bs=1 count=1024 2>/dev/null
    chown munge:munge /etc/munge/munge.key
    chmod 400 /etc/munge/munge.key
  fi
  mkdir -p /run/munge /var/log/munge /var/lib/munge
  chown munge:munge /run/munge /var/log/munge /var/lib/munge
  if ! munge -n </dev/null >/dev/null 2>&1; then
    log "starting munged"
    runuser -u munge -- /usr/sbin/munged >&2
    for _ in $(seq 50); do munge -n </dev/null >/dev/null 2>&1 && break; sleep 0.1; done
  fi

  node="$(hostname -s)"
  cpus="$(nproc)"
  [ "$cpus" -ge 4 ] || cpus=4  # config_overrides below: slurmd takes the CPUs from here, not from the hardware
  mem_mb="$(awk '/MemTotal/ {printf "%d", $2 / 1024 * 0.9}' /proc/meminfo)"
  mkdir -p "$DIR/state" "$DIR/spool"
  cat >"$CONF.new" <<CONF_END
# sb3-td3x: a one-node cluster for the cluster tests (.ci/slurm.sh); not for production
ClusterName=td3x
SlurmctldHost=$node(127.0.0.1)
SlurmUser=root
SlurmdUser=root
AuthType=auth/munge
StateSaveLocation=$DIR/state
SlurmdSpoolDir=$DIR/spool
SlurmctldPidFile=$DIR/slurmctld.pid
SlurmdPidFile=$DIR/slurmd.pid
SlurmctldLogFile=$DIR/slurmctld.log
SlurmdLogFile=$DIR/slurmd.log
SlurmctldPort=${SB3_TD3X_SLURMCTLD_PORT:-6817}
SlurmdPort=${SB3_TD3X_SLURMD_PORT:-6818}
ProctrackType=proctrack/linuxproc
TaskPlugin=task/none
JobAcctGatherType=jobacct_gather/none
AccountingStorageType=accounting_storage/none
SelectType=select/cons_tres
SelectTypeParameters=CR_Core
SchedulerType=sched/backfill
MpiDefault=none
ReturnToService=2
SlurmdParameters=config_overrides
JobRequeue=1
KillWait=30
MinJobAge=600
SlurmdTimeout=60
NodeName=$node NodeAddr=127.0.0.1 CPUs=$cpus RealMemory=$mem_mb State=UNKNOWN
PartitionName=debug Nodes=ALL Default=YES MaxTime=INFINITE State=UP
CONF_END
  if [ -f "$CONF" ] && cmp -s "$CONF" "$CONF.new"; then
    rm "$CONF.new"
  else
    mv "$CONF.new" "$CONF"
    changed=1
  fi

  running() { [ -f "$1" ] && kill -0 "$(cat "$1")" 2>/dev/null; }
  if [ "${changed:-0}" = 1 ]; then  # a new conf: daemons of an old one go
    for pid in "$DIR/slurmd.pid" "$DIR/slurmctld.pid"; do
      running "$pid" && kill "$(cat "$pid")" && sleep 1
    done
  fi
  if ! running "$DIR/slurmctld.pid"; then
    log "starting slurmctld"
    /usr/sbin/slurmctld -f "$CONF" >&2
  fi
  if ! running "$DIR/slurmd.pid"; then
    log "starting slurmd on $node ($cpus CPUs, $mem_mb MB)"
    /usr/sbin/slurmd -f "$CONF" >&2
  fi
  for i in $(seq 120); do
    state="$(sinfo -h -N -n "$node" -o %T 2>/dev/null || true)"
    case "$state" in
      idle|mixed|allocated) break ;;
      down*|drain*) scontrol update nodename="$node" state=resume >/dev/null 2>&1 || true ;;
    esac
    sleep 0.5
  done
  if [ "$state" != idle ] && [ "$state" != mixed ] && [ "$state" != allocated ]; then
    log "the node did not come up (state: '${state:-none}'); see $DIR/slurmctld.log and $DIR/slurmd.log"
    exit 1
  fi
  echo "$CONF"
)

if [ "${BASH_SOURCE[0]}" != "$0" ]; then
  SLURM_CONF="$(_sb3_td3x_start_slurm)" || return 1
  export SLURM_CONF
else
  _sb3_td3x_start_slurm
fi
