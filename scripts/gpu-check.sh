#!/bin/bash
# The GPU measurements of issue 13 (training speed) in one command on a lent GPU machine: the device tool's
# `run` with carry [".whl"] and timeout_s 600, command `bash scripts/gpu-check.sh`. It keeps to BUDGET seconds
# (default 540), most important measurement first, skipping a part that would not fit. It has not yet run on a
# GPU. What it writes to $OUT (the device tool brings back at most 8 files):
#   bench_eager.json     `cotpc bench train` on the GPU, dt / bet / cotpc, both shapes, batch 256 and 4 x 256
#                        (samples/s at 4x the batch: what training several seeds as one model could gain)
#   loop_off.json        the real training loop's loop_timing.json: CoTPC on Moving Maze demos at batch 256
#   bench_graphs.json    the CoTPC step as CUDA graphs (`--compile reduce-overhead`), beside eager
#   loop_reduce-overhead.json  the real loop with `cotpc train --compile reduce-overhead`
#   jobs.txt             JOBS runs sharing the GPU at once (as `reproduce --jobs`): aggregate iterations/s
#   log.txt              everything printed
#
# Before the call, once, here (the GPU machine has torch, h5py, safetensors, tensorboard, tqdm, matplotlib and
# imageio, and cannot download; the rest travels as wheels in the git-ignored .whl/):
#   echo /.whl/ >> .git/info/exclude
#   python3 -m pip download --no-deps --only-binary=:all: --python-version 3.12 --implementation cp \
#     --platform manylinux_2_28_x86_64 --platform manylinux_2_17_x86_64 --platform manylinux2014_x86_64 -d .whl \
#     tyro docstring-parser typeguard shtab gymnasium farama-notifications diffusers==0.41.0 "importlib-metadata<9"
#
# Check the script itself on a CPU, at toy sizes (about 2 minutes):
#   DEVICE=cpu SMALL=1 PY=.venv/bin/python OUT=/tmp/gpu-check bash scripts/gpu-check.sh
set -uo pipefail
OUT=${OUT:-/tmp/gpu-check}
DEVICE=${DEVICE:-cuda}
PY=${PY:-python3}
SMALL=${SMALL:-0}
BUDGET=${BUDGET:-540}
WORK=$(mktemp -d)
mkdir -p "$OUT"
exec > >(tee "$OUT/log.txt") 2>&1
if ls .whl/*.whl > /dev/null 2>&1; then
    $PY -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl || exit 1
    export PYTHONPATH=/tmp/site
fi
export PYTHONPATH=$PWD/src${PYTHONPATH:+:$PYTHONPATH}
if [ "$SMALL" = 1 ]; then  # toy sizes: checks the script, measures nothing
    ITERS=20; DEMOS=40; JOBS=2; SCALES="1 2"; SETTINGS="maniskill"; TIMING="--rounds 1 --iters 1 --warmup 1"
    GRAPHS=default  # CUDA graphs need a GPU; on a CPU reduce-overhead is plain compilation anyway
else
    ITERS=2000; DEMOS=400; JOBS=8; SCALES="1 4"; SETTINGS="maniskill maze"; TIMING="--rounds 5 --iters 10 --warmup 3"
    GRAPHS=reduce-overhead
fi

# part SECONDS TITLE: true if the part fits in what is left of the budget (then print its title)
part() {
    if [ $((SECONDS + $1)) -gt "$BUDGET" ]; then echo "== skipped (${SECONDS}s used of ${BUDGET}s): $2"; return 1; fi
    echo "== $2 (at ${SECONDS}s)"
}
show_bench() {
    $PY - "$1" <<'PYEOF'
import json, sys
r = json.load(open(sys.argv[1]))
print(r.get("gpu") or r["cpu"]["model"], "torch", r["torch"], "matmul peak GFLOP/s", r["matmul_peak_gflops"])
for x in r["rows"]:
    print(f"{x['setting']:<10} {x['policy']:<28} {x['ms_min']:8.2f} ms  {1000 / x['ms_min']:7.1f} it/s  "
          f"{x['samples_per_s']:>9} samples/s  bf16={x['bf16']}")
PYEOF
}
train_loop() {  # MODE SEED OUTDIR: CoTPC on the maze demos at batch 256
    $PY -m cotpc train --data "$WORK/demos/train.h5" --policy cotpc --out "$3" --iters $ITERS --batch-size 256 \
        --n-centres 128 --device "$DEVICE" --compile "$1" --seed "$2" --val-every $ITERS --no-progress
}
export -f train_loop  # so that `timeout N bash -c 'train_loop ...'` can call it
export WORK PY ITERS DEVICE
nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv 2>/dev/null
$PY -c "import torch; print('torch', torch.__version__, 'cuda', torch.cuda.is_available())"

if part 150 "1. the training step, eager (bench train)"; then
    timeout 150 $PY -m cotpc bench train --device "$DEVICE" --policies dt bet cotpc --settings $SETTINGS \
        --batch-scales $SCALES $TIMING --json > "$OUT/bench_eager.json" && show_bench "$OUT/bench_eager.json"
fi
if part 100 "2. the real loop, eager: CoTPC on Moving Maze demos, batch 256, $ITERS iterations"; then
    $PY -m cotpc demos maze --out "$WORK/demos" --train $DEMOS --val 20 --test 20 > /dev/null \
        && $PY -m cotpc segment "$WORK/demos/train.h5" > /dev/null \
        && timeout 90 bash -c 'train_loop off 0 "$WORK/loop-off"' \
        && cp "$WORK/loop-off/loop_timing.json" "$OUT/loop_off.json"
fi
if part 150 "3. the CoTPC step as $GRAPHS (bench train --compile)"; then
    timeout 150 $PY -m cotpc bench train --device "$DEVICE" --policies cotpc --settings $SETTINGS \
        --compile off $GRAPHS $TIMING --json > "$OUT/bench_graphs.json" && show_bench "$OUT/bench_graphs.json"
fi
if [ -f "$WORK/demos/train.h5" ] && part 150 "4. the real loop, --compile $GRAPHS"; then
    timeout 150 bash -c "train_loop $GRAPHS 0 \"\$WORK/loop-$GRAPHS\"" \
        && cp "$WORK/loop-$GRAPHS/loop_timing.json" "$OUT/loop_$GRAPHS.json"
fi
if [ -f "$WORK/demos/train.h5" ] && part 150 "5. $JOBS training runs sharing the device at once (as reproduce --jobs), eager"; then
    start=$SECONDS pids=""
    for seed in $(seq 1 $JOBS); do
        timeout 140 bash -c "train_loop off $seed \"\$WORK/jobs/seed$seed\"" > "$WORK/job$seed.log" 2>&1 &
        pids="$pids $!"
    done
    wait $pids  # (a bare `wait` would also wait for the tee of the log)
    $PY - "$WORK/jobs" $((SECONDS - start)) $JOBS $ITERS > "$OUT/jobs.txt" <<'PYEOF'
import json, sys
from pathlib import Path
root, secs, jobs, iters = Path(sys.argv[1]), int(sys.argv[2]), int(sys.argv[3]), int(sys.argv[4])
rows = [json.loads(p.read_text())[0] for p in sorted(root.glob("seed*/loop_timing.json"))]
print(f"{len(rows)} of {jobs} runs finished, {iters} iterations each at batch 256, all started at once")
for r in rows:
    print(f"  {r['to_step'] / r['wall_s']:.1f} it/s in its loop ({r['wall_s']:.1f} s, "
          f"{100 * r['overhead_share']:.1f}% outside the step)")
slowest = max((r["wall_s"] for r in rows), default=float("nan"))
print(f"aggregate: {len(rows) * iters / slowest:.1f} it/s (all runs' iterations over the slowest loop); "
      f"{secs} s for the part, process starts included")
PYEOF
    cat "$OUT/jobs.txt"
fi
echo "== done at ${SECONDS}s"
rm -rf "$WORK"
