#!/usr/bin/env bash
# make test-portable: the accuracy tests (pytest -m accuracy) on this machine as it is, then with the
# switches that move results the way another processor would (test/conftest.py): OpenCV's optimised code
# paths off, OpenCV on one thread, and two other seeds of every simulated row. Every check's value is
# logged; scripts/accuracy_table.py prints one table and fails on a check within 20 % of its limit.
set -uo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/.."
export ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST
PY=${VENV:-.venv}/bin/python
log=build/accuracy.jsonl
mkdir -p build
rm -f "$log"
status=0
for run in "" "ORCHARD_TEST_CV=noopt" "ORCHARD_TEST_CV=threads1" "ORCHARD_TEST_SEED_OFFSET=1" "ORCHARD_TEST_SEED_OFFSET=2"; do
  echo "[test-portable] accuracy tests ${run:-(no switch)}" >&2
  env $run ORCHARD_ACCURACY_LOG="$log" "$PY" -m pytest test -q -m accuracy -p no:dash --timeout=1800 \
    "$@" || status=1
done
"$PY" scripts/accuracy_table.py "$log" | tee build/accuracy_table.md || status=1
exit $status
