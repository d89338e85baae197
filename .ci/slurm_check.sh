#!/usr/bin/env bash
# The Slurm path end to end on a real single-node Slurm (Debian's slurm-wlm with munge, started
# here; root only): a 3-shard dataset through deploy/slurm/submit.sh, one shard cancelled in the
# middle, `iae-gen status` naming it, its array task resubmitted, status clean, merge complete and
# byte-identical to the same set made in one go. Prints PASS or FAIL; exit status 1 on FAIL.
set -euo pipefail
cd "$(dirname "$0")/.."
ROOT=$PWD
IAE=${IAE:-$ROOT/.venv/bin/iae-gen}
WORK=${WORK:-$(mktemp -d /tmp/iae_slurm_XXXX)}
if ! command -v slurmctld >/dev/null 2>&1; then
    apt-get update -qq
    DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends slurmctld slurmd slurm-client munge >/dev/null
fi
H=$(hostname -s)
mkdir -p "$WORK/state" "$WORK/spool" /var/log/slurm /run/munge /etc/slurm
cat > /etc/slurm/slurm.conf <<CONF
ClusterName=iae_check
SlurmctldHost=$H
SlurmUser=root
AuthType=auth/munge
ProctrackType=proctrack/linuxproc
TaskPlugin=task/none
SelectType=select/cons_tres
SelectTypeParameters=CR_Core
ReturnToService=2
StateSaveLocation=$WORK/state
SlurmdSpoolDir=$WORK/spool
SlurmctldLogFile=/var/log/slurm/slurmctld.log
SlurmdLogFile=/var/log/slurm/slurmd.log
MpiDefault=none
NodeName=$H CPUs=$(nproc) RealMemory=2000 State=UNKNOWN
PartitionName=check Nodes=ALL Default=YES MaxTime=INFINITE State=UP
CONF
[ -s /etc/munge/munge.key ] || dd if=/dev/urandom bs=1 count=1024 of=/etc/munge/munge.key 2>/dev/null
chown munge:munge /etc/munge/munge.key /run/munge 2>/dev/null || true
chmod 400 /etc/munge/munge.key
pgrep -x munged >/dev/null || su -s /bin/sh munge -c munged || munged --force
pkill -x slurmctld || true; pkill -x slurmd || true; sleep 1  # daemons of this check's own config
trap 'pkill -x slurmd || true; pkill -x slurmctld || true' EXIT
slurmctld
slurmd
for _ in $(seq 30); do sinfo -h -o %T 2>/dev/null | grep -q idle && break; sleep 1; done
sinfo
cd "$WORK"
export IAE SBATCH_OPTS="--cpus-per-task=1 --mem=500M"
ARGS=(--resolution 64x32 --seed 5 --views-per-car 2 --background black)
# 20 samples per shard: enough that shard 1 is still rendering when it is cancelled (with the skies
# cached, 4 per shard finished before scancel landed)
N=60
out=$("$ROOT/deploy/slurm/submit.sh" 3 "$WORK/set" $N "${ARGS[@]}")
echo "$out"
array=$(echo "$out" | sed -n 's/^shards: job \([0-9]*\).*/\1/p')
# cancel shard 1 once it has written its first sample (a node lost in the middle of a run)
for _ in $(seq 300); do [ -s "$WORK/set/part1/manifest.jsonl" ] && break; sleep 0.5; done
scancel "${array}_1"
for _ in $(seq 600); do [ -z "$(squeue -h)" ] && break; sleep 1; done
echo "--- status after the cancelled shard"
if "$IAE" status "$WORK"/set/part*; then echo "FAIL: status called a cancelled run ready"; exit 1; fi
[ ! -e "$WORK/set/merged/manifest.jsonl" ] || { echo "FAIL: the merge job merged an unfinished run"; exit 1; }
rerun=$("$IAE" status "$WORK"/set/part* | sed -n 's/.*--array=\([0-9,]*\).*/\1/p' || true)
echo "--- resubmitting array task(s) $rerun"
OUT="$WORK/set" COUNT=$N SHARDS=3 IAE_ARGS="${ARGS[*]}" sbatch --wait $SBATCH_OPTS --array="$rerun" --export=ALL \
    "$ROOT/deploy/slurm/generate.sbatch"
OUT="$WORK/set" sbatch --wait $SBATCH_OPTS --export=ALL "$ROOT/deploy/slurm/merge.sbatch"
"$IAE" status "$WORK"/set/part*
"$IAE" intrinsics --out "$WORK/one_go" --count $N "${ARGS[@]}" --quiet
python3 - "$WORK" <<'PY'
import json, sys
from pathlib import Path
w = Path(sys.argv[1])
rows = lambda p: [(r["index"], r["sha256"]) for r in map(json.loads, (p / "manifest.jsonl").read_text().splitlines())]
merged, one = rows(w / "set" / "merged"), rows(w / "one_go")
assert json.loads((w / "set" / "merged" / "dataset.json").read_text())["complete"], "merged set incomplete"
assert merged == one, "merged samples differ from the set made in one go"
print(f"PASS: {len(merged)} samples in 3 Slurm shards, shard 1 cancelled and repaired, merged = one go, byte for byte")
PY
