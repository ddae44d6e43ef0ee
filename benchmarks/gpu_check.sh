#!/usr/bin/env bash
# The GPU check: one command on a machine with a CUDA GPU (about 5 minutes
# on an H100). From the repository root:
#
#   bash benchmarks/gpu_check.sh [--out DIR]     # default DIR: results/gpu_check
#   bash benchmarks/gpu_check.sh --dry-run       # the same steps on the CPU, tiny
#
# Steps, each timed:
#   1. install what is missing (the package and its test extra; nothing when
#      it imports already: a GPU machine may have no network);
#   2. the CUDA tests (the fused Triton kernel, the tracker on CUDA; with
#      --dry-run the kernel's test runs in Triton's CPU interpreter);
#   3. tg-nebp bench --device cuda --particles 50000 --batch 8;
#   4. on 8 test realizations at K = 50,000: BP, marginalized BP (M = 16,
#      regularized), Gaussian BP, and NEBP, paper and equivariant variants,
#      each trained for a few steps first;
#   5. the paper preset, shortened (reproduce --preset paper-short).
# Everything goes to DIR, and DIR/summary.json gathers every figure, the
# device's name and each step's seconds. A failing step stops the check
# (exit status of that step), and summary.json says which step failed.
set -euo pipefail
cd "$(dirname "$0")/.."

OUT=results/gpu_check
DRY=0
usage() {
  cat <<'EOF'
usage: bash benchmarks/gpu_check.sh [--out DIR] [--dry-run] [--help]

The GPU check: the CUDA tests, tg-nebp bench, BP, marginalized BP, Gaussian
BP and NEBP (both variants) at K = 50,000 on 8 test realizations, and the
shortened paper preset, each step timed; DIR/summary.json gathers every
figure.

  --out DIR   output folder (default: results/gpu_check)
  --dry-run   the same steps on the CPU, tiny (Triton's CPU interpreter)
  --help      this text
EOF
}
fail() {  # one error line, exit 2
  echo "error: $1" >&2
  exit 2
}
while [ $# -gt 0 ]; do
  case "$1" in
    --dry-run) DRY=1 ;;
    --out)
      [ $# -ge 2 ] && [ -n "$2" ] && [ "${2#-}" = "$2" ] \
        || fail "--out needs a folder (--out DIR)"
      OUT="$2"; shift ;;
    --help|-h) usage; exit 0 ;;
    *) fail "unknown option '$1' (use --dry-run, --out DIR, --help)" ;;
  esac
  shift
done
if [ -e "$OUT" ] && [ ! -d "$OUT" ]; then
  fail "--out '$OUT' is a file, not a folder"
fi

if [ "$DRY" = 1 ]; then
  DEVICE=cpu; K=200; REAL=2; BENCH=(--particles 200 --batch 2 --repeats 2 --steps 2)
  TRAIN=(--realizations 2 --val-realizations 1 --epochs 1)
  export TRITON_INTERPRET=1
else
  DEVICE=cuda; K=50000; REAL=8; BENCH=(--particles 50000 --batch 8)
  TRAIN=(--realizations 4 --val-realizations 2 --epochs 1)
fi
PY=${PYTHON:-python3}
ROOT="$OUT/datasets"
mkdir -p "$OUT" 2>/dev/null || fail "--out '$OUT' cannot be created"
STEPS="$OUT/steps.tsv"
: > "$STEPS"

step() {  # step NAME COMMAND...: runs it, logs to DIR/NAME.log, times it
  local name=$1; shift
  local start=$SECONDS rc=0
  echo "== $name: $*"
  "$@" > "$OUT/$name.log" 2>&1 || rc=$?
  printf '%s\t%s\t%s\n' "$name" "$((SECONDS - start))" "$rc" >> "$STEPS"
  if [ "$rc" != 0 ]; then
    tail -n 20 "$OUT/$name.log" >&2
    summarize
    echo "error: step '$name' failed with status $rc (log: $OUT/$name.log)" >&2
    exit "$rc"
  fi
}

summarize() {
  "$PY" - "$OUT" "$DEVICE" "$DRY" <<'EOF'
import datetime, json, sys
from pathlib import Path
out, device, dry = Path(sys.argv[1]), sys.argv[2], sys.argv[3] == '1'
try:
    import torch
    name = (torch.cuda.get_device_name() if device == 'cuda'
            and torch.cuda.is_available() else 'cpu')
    version = torch.__version__
except Exception as e:  # the install step failed
    name, version = f'unknown ({e})', None
summary = dict(device=name, torch=version, dry_run=dry,
               date=datetime.datetime.now(datetime.timezone.utc).isoformat(
                   timespec='seconds'), steps={}, bench=[], methods={})
for line in (out / 'steps.tsv').read_text().splitlines():
    step, seconds, rc = line.split('\t')
    summary['steps'][step] = dict(seconds=int(seconds), status=int(rc))
bench = out / 'bench.log'
if bench.exists():
    summary['bench'] = [json.loads(l) for l in bench.read_text().splitlines()
                        if l.startswith('{')]
for metrics in sorted(out.glob('*/metrics.json')):
    for method, entry in json.loads(metrics.read_text()).items():
        summary['methods'][f'{metrics.parent.name}/{method}'] = entry
tests = out / 'tests.log'
if tests.exists():
    summary['tests'] = tests.read_text().strip().splitlines()[-1]
(out / 'summary.json').write_text(json.dumps(summary, indent=1) + '\n')
print(f"summary -> {out / 'summary.json'}")
EOF
}

if ! "$PY" -c "import tg_nebp, torch_geometric, pytest" 2>/dev/null; then
  step install "$PY" -m pip install -q -e ".[test]"
fi
if [ "$DRY" = 1 ]; then
  step tests "$PY" -m pytest -q -p no:cacheprovider tests/ops tests/filters/particle/test_particle_bp_cuda.py
else
  "$PY" -c "import sys, torch; sys.exit(not torch.cuda.is_available())" \
    || fail "no CUDA device here (use --dry-run on a CPU)"
  step tests "$PY" -m pytest -q -p no:cacheprovider -rs tests/ops tests/filters/particle/test_particle_bp_cuda.py \
    tests/test_training_distributed.py tests/nn/conv
fi
step bench "$PY" -m tg_nebp bench --device "$DEVICE" "${BENCH[@]}" --json --root "$ROOT"
COMMON=(--device "$DEVICE" --realizations "$REAL" --seed 0 --root "$ROOT" --quiet)
step bp "$PY" -m tg_nebp evaluate --method bp --particles "$K" "${COMMON[@]}" --out "$OUT/bp"
step bp_marginalized "$PY" -m tg_nebp evaluate --method bp --particles "$K" --samples 16 \
  --regularize "${COMMON[@]}" --out "$OUT/bp_marginalized"
step gbp "$PY" -m tg_nebp evaluate --method gbp "${COMMON[@]}" --out "$OUT/gbp"
for variant in paper equivariant; do
  step "train_$variant" "$PY" -m tg_nebp train --variant "$variant" --particles "$K" \
    "${TRAIN[@]}" --device "$DEVICE" --root "$ROOT" --out "$OUT/nebp_$variant" --quiet
  step "nebp_$variant" "$PY" -m tg_nebp evaluate --method nebp --particles "$K" \
    --checkpoint "$OUT/nebp_$variant/nebp.pt" "${COMMON[@]}" --out "$OUT/nebp_$variant"
done
if [ "$DRY" = 1 ]; then  # the shortened preset at a CPU's size
  step reproduce "$PY" - "$OUT/reproduce" "$ROOT" <<'EOF'
import sys
from tg_nebp.experiments import reproduce as r
r.PRESETS['paper-short'] = dict(r.PRESETS['paper-short'], particles=100,
                                train_realizations=2, val_realizations=1,
                                epochs=1, test_realizations=2)
r.reproduce('paper-short', 'cpu', sys.argv[1], sys.argv[2])
EOF
else
  step reproduce "$PY" -m tg_nebp reproduce --preset paper-short --device cuda \
    --root "$ROOT" --out "$OUT/reproduce" --quiet
fi
summarize
