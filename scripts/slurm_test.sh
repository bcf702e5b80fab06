#!/usr/bin/env bash
# A tile plan through a real Slurm: starts munge + slurmctld + slurmd on localhost with a minimal
# single-node configuration in a temp folder, submits the plan's job arrays and merge job
# (P/slurm.sh) on a small SIMULATED scene, waits, and compares the merged labels with
# `gs4city run-plan` on the same plan made again (byte for byte); then stops the daemons it
# started (by pid) and removes the temp folder. Installs nothing: `scripts/setup.sh` installs
# slurm-wlm and munge. Needs root (the daemons run as root, no systemd).
#
#   bash scripts/slurm_test.sh [path/to/gs4city]     (default: target/release/gs4city)
#
# With SLURM_PLAN=P (a plan made by `gs4city tile`), the same daemons run that plan's job arrays
# and merge job instead (P/slurm.sh; no comparison, no time limit) and stop when the merge is
# done: the Slurm run of a benchmark (scripts/city_scaling.sh, SLURM=1). The node offers
# SLURM_MEMORY_MB (8000) of memory to the jobs.
#
# Exit 0: passed; 1: failed; 77: cannot run here (not root, or Slurm/munge missing).
set -euo pipefail
cd "$(dirname "$0")/.."
BIN="$(realpath "${1:-target/release/gs4city}")"
skip() { echo "SKIPPED: slurm_test: $*"; exit 77; }
[ "$(id -u)" = 0 ] || skip "needs root (slurmd and munged run as root here)"
for c in munged slurmctld slurmd sbatch squeue sinfo; do
  command -v "$c" >/dev/null || skip "$c missing (bash scripts/setup.sh installs slurm-wlm and munge)"
done
[ -x "$BIN" ] || { echo "slurm_test: $BIN is not an executable gs4city (cargo build --release)"; exit 1; }

T="$(mktemp -d /tmp/gs4city-slurm.XXXXXX)"
PIDS=()
MUNGE_STARTED=0
cleanup() {
  for p in "${PIDS[@]}"; do kill "$p" 2>/dev/null || true; done
  if [ "$MUNGE_STARTED" = 1 ] && [ -f "$T/munged.pid" ]; then kill "$(cat "$T/munged.pid")" 2>/dev/null || true; fi
  for p in "${PIDS[@]}"; do wait "$p" 2>/dev/null || true; done
  rm -rf "$T"
}
trap cleanup EXIT

# munge: the key the package made (or a new one), its own socket and pid file in $T.
mkdir -p /run/munge /var/log/munge /var/lib/munge /etc/munge
chown munge:munge /run/munge /var/log/munge /var/lib/munge 2>/dev/null || true
if [ ! -s /etc/munge/munge.key ]; then
  if command -v mungekey >/dev/null; then mungekey --create --keyfile=/etc/munge/munge.key; else
    dd if=/dev/urandom bs=1 count=1024 of=/etc/munge/munge.key 2>/dev/null; fi
  chown munge:munge /etc/munge/munge.key; chmod 400 /etc/munge/munge.key
fi
SOCK="$T/munge.socket"
munged --force --socket="$SOCK" --pid-file="$T/munged.pid" --log-file="$T/munged.log" --seed-file="$T/munge.seed"
MUNGE_STARTED=1

HOST="$(hostname -s)"
mkdir -p "$T/state" "$T/spool" "$T/log"
cat > "$T/slurm.conf" <<EOF
ClusterName=gs4city-test
SlurmctldHost=$HOST
SlurmUser=root
SlurmdUser=root
AuthType=auth/munge
AuthInfo=socket=$SOCK
CredType=cred/munge
SlurmctldPort=16817
SlurmdPort=16818
StateSaveLocation=$T/state
SlurmdSpoolDir=$T/spool
SlurmctldPidFile=$T/slurmctld.pid
SlurmdPidFile=$T/slurmd.pid
SlurmctldLogFile=$T/log/slurmctld.log
SlurmdLogFile=$T/log/slurmd.log
ProctrackType=proctrack/linuxproc
TaskPlugin=task/none
JobAcctGatherType=jobacct_gather/none
AccountingStorageType=accounting_storage/none
SelectType=select/cons_tres
SelectTypeParameters=CR_Core
ReturnToService=2
MpiDefault=none
NodeName=$HOST CPUs=$(nproc) RealMemory=${SLURM_MEMORY_MB:-8000} State=UNKNOWN
PartitionName=test Nodes=$HOST Default=YES MaxTime=INFINITE State=UP
EOF
export SLURM_CONF="$T/slurm.conf"
slurmctld -D -f "$SLURM_CONF" > "$T/log/slurmctld.out" 2>&1 &
PIDS+=($!)
slurmd -D -f "$SLURM_CONF" > "$T/log/slurmd.out" 2>&1 &
PIDS+=($!)
up=0
for _ in $(seq 1 60); do
  if sinfo -h -o '%t' 2>/dev/null | grep -qE '^idle'; then up=1; break; fi
  sleep 1
done
if [ "$up" != 1 ]; then
  echo "slurm_test: the node did not come up within 60 s"; tail -20 "$T/log/"*.log || true; exit 1
fi
echo "slurm_test: single-node Slurm up on $HOST ($(sinfo -h -o '%D node(s), %c CPUs, %t'))"

wait_jobs() { # job ids (comma-separated), seconds at most
  for _ in $(seq 1 "$2"); do
    [ -z "$(squeue -h -j "$1" 2>/dev/null)" ] && return 0
    sleep 1
  done
  return 1
}

if [ -n "${SLURM_PLAN:-}" ]; then
  P="$(realpath "$SLURM_PLAN")"
  GS4CITY="$BIN" bash "$P/slurm.sh" | tee "$T/submit.txt"
  jobs=$(grep -oE 'job [0-9]+' "$T/submit.txt" | awk '{print $2}' | paste -sd, -)
  wait_jobs "$jobs" 86400 || { echo "slurm_test: jobs $jobs still queued after a day"; exit 1; }
  [ -f "$P/merged/summary.json" ] || { echo "slurm_test: the merge job left no $P/merged/summary.json"; tail -5 "$P/slurm/logs/"*; exit 1; }
  echo "slurm_test: plan $P ran through Slurm and merged"
  exit 0
fi

# A small SIMULATED scene and two identical plans of two tiles each.
"$BIN" -q synth --preset small --seed 3 --out "$T/scene"
"$BIN" -q tile --scene "$T/scene" --size 10 --margin 4 --out "$T/plan_slurm" > /dev/null
"$BIN" -q tile --scene "$T/scene" --size 10 --margin 4 --out "$T/plan_local" > /dev/null
ntiles=$(python3 -c "import json,sys; print(sum(t['runnable'] for t in json.load(open(sys.argv[1]))['tiles']))" "$T/plan_slurm/plan.json")
[ "$ntiles" -ge 2 ] || { echo "slurm_test: expected ≥ 2 runnable tiles, got $ntiles"; exit 1; }

GS4CITY="$BIN" bash "$T/plan_slurm/slurm.sh" | tee "$T/submit.txt"
jobs=$(grep -oE 'job [0-9]+' "$T/submit.txt" | awk '{print $2}' | paste -sd, -)
if ! wait_jobs "$jobs" 1200; then echo "slurm_test: jobs $jobs still queued after 20 min"; squeue; exit 1; fi
for f in "$T/plan_slurm/slurm/logs/"*.out; do echo "--- $f"; tail -3 "$f"; done
[ -f "$T/plan_slurm/merged/summary.json" ] || { echo "slurm_test: the merge job left no merged/summary.json"; exit 1; }
for t in "$T/plan_slurm/tiles/"*/; do
  python3 -c "import json,sys; s=json.load(open(sys.argv[1])); assert s['ok'], s" "$t/status.json"
done

"$BIN" -q run-plan "$T/plan_local" --jobs 2 > /dev/null
python3 - "$T" <<'EOF'
import json, sys, numpy as np
t = sys.argv[1]
a = np.load(f"{t}/plan_slurm/merged/lift/gaussians.npy")
b = np.load(f"{t}/plan_local/merged/lift/gaussians.npy")
assert a.shape == b.shape and a.shape[1] == 2, (a.shape, b.shape)
assert (a == b).all(), f"{(a != b).any(axis=1).sum()} Gaussians differ between Slurm and run-plan"
sa = json.load(open(f"{t}/plan_slurm/merged/summary.json"))
sb = json.load(open(f"{t}/plan_local/merged/summary.json"))
assert sa["labelled"] == sb["labelled"] and sa["labelled"] > 0.8 * sa["gaussians"], (sa["labelled"], sb["labelled"])
assert sa["paper_fine_miou"] == sb["paper_fine_miou"], (sa["paper_fine_miou"], sb["paper_fine_miou"])
print(f"slurm_test: Slurm and run-plan agree on all {a.shape[0]} Gaussians "
      f"({sa['labelled']} labelled, test-view fine mIoU {100 * sa['paper_fine_miou']:.2f})")
EOF
echo "slurm_test: passed"
