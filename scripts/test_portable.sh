#!/usr/bin/env bash
# make test-portable: the accuracy tests (pytest -m accuracy) on this machine as it is, then with the
# switches that move results the way another processor would (test/conftest.py): OpenCV's optimised code
# paths off, OpenCV on one thread, and two other seeds of every simulated row. Every check's value is
# logged; scripts/accuracy_table.py prints one table and fails on a check within 20 % of its limit.
# PORTABLE_JOBS=N runs N of the five runs at a time (default 1; each run's output: build/portable_*.log).
set -uo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/.."
export ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST
PY=${VENV:-.venv}/bin/python
JOBS=${PORTABLE_JOBS:-1}
log=build/accuracy.jsonl
mkdir -p build
rm -f "$log" build/portable_*.log build/portable_*.rc
runs=("default" "ORCHARD_TEST_CV=noopt" "ORCHARD_TEST_CV=threads1" "ORCHARD_TEST_SEED_OFFSET=1" "ORCHARD_TEST_SEED_OFFSET=2")
one_run() {  # $1: index, $2: switch (or "default")
  local sw=$2 name
  name=$(echo "$sw" | tr '=' '-')
  [ "$sw" = default ] && sw=""
  echo "[test-portable] accuracy tests ${2}" >&2
  env $sw ORCHARD_ACCURACY_LOG="$log" "$PY" -m pytest test -q -m accuracy -p no:dash --timeout=1800 \
    "${@:3}" > "build/portable_$1_$name.log" 2>&1
  echo $? > "build/portable_$1_$name.rc"
  tail -n 1 "build/portable_$1_$name.log" >&2
}
for i in "${!runs[@]}"; do
  while [ "$(jobs -rp | wc -l)" -ge "$JOBS" ]; do sleep 2; done
  one_run "$i" "${runs[$i]}" "$@" &
done
wait
status=0
for rc in build/portable_*.rc; do [ "$(cat "$rc")" = 0 ] || status=1; done
"$PY" scripts/accuracy_table.py "$log" | tee build/accuracy_table.md || status=1
exit $status
