#!/usr/bin/env bash
# Train the bunny GENERIC network on a dense set of load positions: the recipe of `bunny-128x6` (one-step
# phase, then whole-rollout BPTT), with ~700 training positions instead of 71 (scripts/bunny_dense_positions.py).
# Meant for a GPU machine; every stage is resumable and skips what is already there.
#
#   scripts/bunny_dense_train.sh data     # FEM data: the seed-0 data set (val/test) and the dense positions
#   scripts/bunny_dense_train.sh phase1   # one-step loss, from scratch      -> runs/dense-p1/best/model.npz
#   scripts/bunny_dense_train.sh phase2   # BPTT over 20-step rollouts       -> runs/dense-p2/best/model.npz
#
# Environment: PY (python, default python3), REF_CASES (100), DENSE_LIMIT (all), GEN_BATCH (128),
# P1_EPOCHS (24), P2_EPOCHS (8), P2_BATCH (8), P1_TIME/P2_TIME (a time limit in s; default none),
# INIT (phase2's warm start; default runs/dense-p1, or tignn_jax/models/bunny-dense-128x6/model.npz),
# SIZE ("--set hidden=128 --set passes=6"). On one H100: data 219 s, 17.3 s per one-step epoch, 29 s per BPTT
# epoch, plus about 2 min to load the data and compile. Session 29's run (lab notes) was cut by its device time
# after 17 of the 24 one-step epochs; its BPTT phase started from epoch 16's model.
set -euo pipefail
PY=${PY:-python3}
STAGE=${1:?stage: data, phase1 or phase2}
GEN=(-m tignn_jax.cli generate bunny --integrator implicit --density 1e-3 --load-radius 5 --rise-frames 10
     --batch "${GEN_BATCH:-128}" --no-progress)
OPTS=(--set edge_strain=true --set node_position=true --set force_port=true --set load_context=true
      --set elastic_port=true --set port_hops=2)
SIZE=${SIZE:-"--set hidden=128 --set passes=6"}
mkdir -p data runs
case "$STAGE" in
  data)
    # the FEM's float32 products at full precision (a GPU may otherwise run them in TF32)
    export JAX_DEFAULT_MATMUL_PRECISION=${JAX_DEFAULT_MATMUL_PRECISION:-highest}
    t0=$(date +%s)
    [ -f data/bunny.npz ] || $PY "${GEN[@]}" --seed 0 --cases "${REF_CASES:-100}" --out data/bunny.npz
    t1=$(date +%s); echo "reference set: $((t1 - t0)) s"
    $PY scripts/bunny_dense_positions.py ${DENSE_LIMIT:+--limit $DENSE_LIMIT} > data/dense_nodes.txt
    [ -f data/bunny_dense.npz ] || $PY "${GEN[@]}" --load-nodes "$(cat data/dense_nodes.txt)" --out data/bunny_dense.npz
    t2=$(date +%s); echo "dense set: $((t2 - t1)) s"
    [ -f data/bunny_all.npz ] || $PY scripts/concat_data.py data/bunny.npz data/bunny_dense.npz --train-later \
        --out data/bunny_all.npz
    echo "assembled: $(( $(date +%s) - t2 )) s" ;;
  phase1)
    $PY -m tignn_jax.cli train --data data/bunny_all.npz --config bunny --run-dir runs/dense-p1 --no-progress \
        ${P1_TIME:+--time-limit $P1_TIME} $SIZE "${OPTS[@]}" --set batch_size=16 --set epochs="${P1_EPOCHS:-24}" \
        --set lr=1e-3 --set warmup_steps=200 --set eval_every=1 --set ckpt_every=1 ;;
  phase2)
    $PY -m tignn_jax.cli train --data data/bunny_all.npz --config bunny --run-dir runs/dense-p2 --no-progress \
        --init-from "${INIT:-runs/dense-p1}" ${P2_TIME:+--time-limit $P2_TIME} $SIZE "${OPTS[@]}" --set unroll=20 \
        --set bptt=true --set snapshot_loss=true --set noise=0.1 --set batch_size="${P2_BATCH:-8}" --set lr=3e-4 \
        --set lr_end=3e-5 --set warmup_steps=20 --set epochs="${P2_EPOCHS:-8}" --set eval_every=1 \
        --set ckpt_every=1 ;;
  *) echo "unknown stage $STAGE (data, phase1, phase2)" >&2; exit 2 ;;
esac
