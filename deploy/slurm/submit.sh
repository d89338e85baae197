#!/usr/bin/env bash
# Submit a sharded dataset and its merge in one go:
#   deploy/slurm/submit.sh SHARDS OUT COUNT [iae-gen options ...]
#   deploy/slurm/submit.sh 8 /scratch/intrinsics 20000 --seed 0 --resolution 512x256
# The merge starts when every shard task has ended (afterany) and refuses an unfinished run.
# SBATCH_OPTS adds sbatch options to both jobs (e.g. "--partition=cpu --cpus-per-task=8").
set -euo pipefail
[ $# -ge 3 ] || { echo "usage: $0 SHARDS OUT COUNT [iae-gen options ...]" >&2; exit 2; }
SHARDS=$1 OUT=$2 COUNT=$3; shift 3
HERE=$(cd "$(dirname "$0")" && pwd)
export OUT COUNT SHARDS IAE_ARGS="$*"
# shellcheck disable=SC2086  # SBATCH_OPTS holds several options
ARRAY=$(sbatch --parsable ${SBATCH_OPTS:-} --array=0-$((SHARDS - 1)) --export=ALL "$HERE/generate.sbatch")
# shellcheck disable=SC2086
MERGE=$(sbatch --parsable ${SBATCH_OPTS:-} --dependency=afterany:"$ARRAY" --export=ALL "$HERE/merge.sbatch")
echo "shards: job $ARRAY (array 0-$((SHARDS - 1))); merge: job $MERGE"
