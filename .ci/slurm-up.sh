#!/usr/bin/env bash
# A single-node SLURM on this machine, for the tests of `cluster: {kind: slurm}`.
#
#   bash .ci/slurm-up.sh      # as root (or with sudo), on Debian or Ubuntu
#
# Installs Debian's slurm-wlm and munge when missing, writes a minimal slurm.conf for this
# machine (one node with its CPUs and memory, partition "debug"; no cgroups, no accounting),
# starts munged, slurmctld and slurmd directly as daemons (no systemd needed) and waits until
# `sinfo` shows the node idle. Running it again when SLURM is already up takes a second.
# Daemon logs: /var/log/slurm/. Stop: `scontrol shutdown` (slurmctld and slurmd) and
# `kill $(cat /run/munge/munged.pid)`.
set -euo pipefail
start=$(date +%s)
done_in() { echo "slurm-up: $1 ($(( $(date +%s) - start )) s)"; }

SUDO=""; [ "$(id -u)" -eq 0 ] || SUDO="sudo -n"   # never a password prompt: fail instead
node=$(hostname -s)

node_state() { sinfo -h -N -n "$node" -o %T 2>/dev/null | head -1 | tr -d '*~#'; }
header="# written by Persona's .ci/slurm-up.sh: a single-node SLURM for tests"

alive() { [ -f "$1" ] && $SUDO kill -0 "$(cat "$1")" 2>/dev/null; }

if command -v sinfo >/dev/null && [[ "$(node_state)" =~ ^(idle|mixed|allocated)$ ]] \
   && alive /run/slurmctld.pid && alive /run/slurmd.pid; then
  done_in "SLURM already up, node $node $(node_state)"; exit 0
fi
if [ -f /etc/slurm/slurm.conf ] && [ "$(head -1 /etc/slurm/slurm.conf)" != "$header" ]; then
  echo "slurm-up: /etc/slurm/slurm.conf was not written by this script: leaving this machine's SLURM alone" >&2
  exit 1
fi

if ! command -v slurmctld >/dev/null || ! command -v munged >/dev/null; then
  command -v apt-get >/dev/null || { echo "slurm-up: no apt-get: this script installs SLURM on Debian/Ubuntu only" >&2; exit 1; }
  echo "slurm-up: installing slurm-wlm and munge"
  $SUDO apt-get update -qq
  DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq --no-install-recommends slurm-wlm munge >/dev/null
fi

# munge: the key the package made (or a new one), the daemon run as its own user
[ -s /etc/munge/munge.key ] || $SUDO mungekey --create --keyfile=/etc/munge/munge.key
$SUDO chown munge:munge /etc/munge/munge.key && $SUDO chmod 600 /etc/munge/munge.key
$SUDO mkdir -p /run/munge /var/log/munge /var/lib/munge
$SUDO chown munge:munge /run/munge /var/log/munge /var/lib/munge
if ! munge -n </dev/null >/dev/null 2>&1; then
  $SUDO runuser -u munge -- /usr/sbin/munged
  for _ in $(seq 50); do munge -n </dev/null >/dev/null 2>&1 && break; sleep 0.1; done
fi
munge -n </dev/null | unmunge >/dev/null || { echo "slurm-up: munged does not answer (see /var/log/munge/munged.log)" >&2; exit 1; }

# slurm.conf: this machine as the one node, with what slurmd itself detects (CPUs, memory)
hardware=$(slurmd -C | head -1 | sed 's/^NodeName=[^ ]* //')
conf=$(cat <<EOF
$header
ClusterName=persona
SlurmctldHost=$node
SlurmUser=root
SlurmdUser=root
AuthType=auth/munge
StateSaveLocation=/var/spool/slurmctld
SlurmdSpoolDir=/var/spool/slurmd
SlurmctldPidFile=/run/slurmctld.pid
SlurmdPidFile=/run/slurmd.pid
SlurmctldLogFile=/var/log/slurm/slurmctld.log
SlurmdLogFile=/var/log/slurm/slurmd.log
ProctrackType=proctrack/linuxproc
TaskPlugin=task/none
JobAcctGatherType=jobacct_gather/none
AccountingStorageType=accounting_storage/none
SelectType=select/cons_tres
SelectTypeParameters=CR_Core_Memory
MpiDefault=none
ReturnToService=2
SlurmdTimeout=60
NodeName=$node NodeAddr=127.0.0.1 $hardware State=UNKNOWN
PartitionName=debug Nodes=$node Default=YES MaxTime=INFINITE State=UP
EOF
)
$SUDO mkdir -p /etc/slurm /var/spool/slurmctld /var/spool/slurmd /var/log/slurm
if [ "$(cat /etc/slurm/slurm.conf 2>/dev/null)" != "$conf" ]; then
  echo "$conf" | $SUDO tee /etc/slurm/slurm.conf >/dev/null
  scontrol ping >/dev/null 2>&1 && $SUDO scontrol reconfigure || true
fi

alive /run/slurmctld.pid || $SUDO /usr/sbin/slurmctld
alive /run/slurmd.pid || $SUDO /usr/sbin/slurmd

for _ in $(seq 120); do
  state=$(node_state)
  case "$state" in
    idle|mixed|allocated) done_in "SLURM up, node $node $state"; exit 0 ;;
    down|drain*) $SUDO scontrol update NodeName="$node" State=RESUME 2>/dev/null || true ;;
  esac
  sleep 0.5
done
echo "slurm-up: node $node is not idle after 60 s (state: ${state:-unknown}); see /var/log/slurm/" >&2
exit 1
