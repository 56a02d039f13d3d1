#!/usr/bin/env bash
# The checks that need a GPU, in one run (CI has none): the model's tests on CUDA (tests/uncertainty/test_cuda.py
# and the CLI's --device cuda tests run only there), fused vs per-member scoring on the GPU, the accuracy and
# calibration figure trained on the GPU, the whole loop (`activecollect run`, its default settings) on that
# machine (its retrains and scoring stay on the CPU by design: it checks that nothing breaks where CUDA is there),
# and whether two `bench loop --deterministic` runs on the device repeat to the last digit.
#
# Usage, from the repository root on a machine with CUDA and PyTorch:
#   bash bench/device_checks.sh OUTDIR
# Our other dependencies can come as wheels in .whl/ (for a machine with PyTorch but no package index): they are
# installed into /tmp/site first (WHEELS=DIR for another folder). PYTHON=... picks the interpreter (default python3);
# DEVICE=cpu rehearses the same steps on a machine without a GPU (the CUDA-only tests are then skipped; SLOW=N
# multiplies every step's time limit, e.g. SLOW=3 on a 2-core CPU). EPOCHS=N sets the figure's training epochs
# (default 16 on CUDA, where the accuracy and the calibration figure are both met, ~1 min on an H100; 4 on the
# CPU, the accuracy figure's 2 minutes). Each step has a time limit and the script goes on after a failing step;
# the summary at the end says which failed (exit 1 if any did). Results go to OUTDIR (*.log, *.json).
set -u
OUT=${1:?usage: bash bench/device_checks.sh OUTDIR}
mkdir -p "$OUT"
export PYTHONUNBUFFERED=1 PYTHONPATH=$PWD
PY=${PYTHON:-python3}
DEVICE=${DEVICE:-cuda}
WHEELS=${WHEELS:-.whl}
SLOW=${SLOW:-1}
if [ "$DEVICE" = cuda ]; then EPOCHS=${EPOCHS:-16}; else EPOCHS=${EPOCHS:-4}; fi
WORK=$(mktemp -d)  # the data directories of the figure and of the run
if compgen -G "$WHEELS/*.whl" > /dev/null; then
    $PY -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site "$WHEELS"/*.whl \
        || { echo "wheels did not install"; exit 1; }
    export PYTHONPATH=/tmp/site:$PWD
fi
failed=()
step() {  # step NAME SECONDS COMMAND...: run it with a limit, its output in OUTDIR/NAME.log
    local name=$1 limit=$2
    shift 2
    local t0=$SECONDS
    timeout $((limit * SLOW)) "$@" > "$OUT/$name.log" 2>&1
    local rc=$?
    echo "== $name: exit $rc in $((SECONDS - t0)) s"
    tail -n 4 "$OUT/$name.log" | cut -c 1-300
    [ $rc -eq 0 ] || failed+=("$name")
}

if [ "$DEVICE" = cuda ]; then
    nvidia-smi -L
    $PY -c 'import torch; print("torch", torch.__version__, "cuda", torch.version.cuda, torch.cuda.get_device_name())'
    $PY -c 'import torch, sys; sys.exit(0 if torch.cuda.is_available() else 1)' || { echo "no CUDA here"; exit 1; }
fi

step tests 150 $PY -m pytest -q -p no:cacheprovider tests/uncertainty tests/test_cli_device.py tests/test_cli_models.py
for batch in 1 48 480; do
    step "score_b$batch" 40 $PY -m orchestrator bench score --device "$DEVICE" --batch $batch --seconds 8 --json
done
step "figures_$DEVICE" 150 $PY bench/uncertainty_figures.py --data "$WORK/figures" --skip ood,bench \
    --device "$DEVICE" --epochs "$EPOCHS" --json "$OUT/figures_$DEVICE.json"
step run 120 $PY -m orchestrator run --data "$WORK/run"
cp "$WORK"/run/reports/*/summary.json "$OUT/run_summary.json" 2>/dev/null
# Two runs of one small `bench loop --deterministic` must give the same points to the last digit (without it the
# GPU's fastest kernels made runs differ by up to 0.8 %); an operation torch has no deterministic kernel for warns.
for r in 1 2; do
    step "loop_deterministic_$r" 90 $PY -m orchestrator bench loop --seeds 1 --budget 32 --device "$DEVICE" \
        --deterministic --json --out "$WORK/loop$r"
done
step loop_repeats 20 $PY -c 'import json, sys
points = [[{k: v for k, v in p.items() if k != "train_s"} for p in json.load(open(f))["points"]] for f in sys.argv[1:]]
print("the two runs gave the same points" if points[0] == points[1] else f"the two runs differ: {points}")
sys.exit(points[0] != points[1])' "$WORK/loop1/summary.json" "$WORK/loop2/summary.json"
grep -h "does not have a deterministic" "$OUT"/loop_deterministic_*.log | sort -u | head -5

if [ ${#failed[@]} -gt 0 ]; then
    echo "failed: ${failed[*]}"
    exit 1
fi
echo "all passed"
