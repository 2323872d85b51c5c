#!/usr/bin/env bash
# Issue 23's acceptance on N simulated field hours at once, one process per seed and engine
# (a many-core machine: OMP threads 1 each): benchmarks/field_hour.py's line per seed into
# $OUT/joint.jsonl and $OUT/linear.jsonl. Usage: [P=16] bash benchmarks/field_device.sh FIRST LAST [DURATION]
set -u
first=$1; last=$2; dur=${3:-3600}
out=${OUT:-/tmp/field_out}; mkdir -p "$out"
export OMP_NUM_THREADS=1 OPENBLAS_NUM_THREADS=1 MKL_NUM_THREADS=1 PYTHONPATH=$PWD/src PYTHONUNBUFFERED=1
one() {  # seed engine
  python3 benchmarks/field_hour.py --seeds "$1" --duration "$dur" --engine "$2" 2>>"$out/err_$2.log" \
    | grep '^{' >> "$out/$2.jsonl"
}
export -f one; export dur out
{ for s in $(seq "$first" "$last"); do echo "$s joint"; done
  for s in $(seq "$first" "$last"); do echo "$s linear"; done; } | xargs -P "${P:-16}" -n 2 bash -c 'one "$0" "$1"'
echo "done: $(wc -l < "$out/joint.jsonl") joint, $(wc -l < "$out/linear.jsonl") linear"
