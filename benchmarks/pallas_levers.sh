#!/usr/bin/env bash
# Issue 15 on the GPU: the Pallas whole-rollout kernel checked against the fused step, then the
# standard problem's NNSVGD step time for kernel block sizes and both simulation steps, then the
# gradient cost. Run from the repo root: bash benchmarks/pallas_levers.sh [part]
set -u
part="${1:-all}"
step() {
  timeout 200 python3 -m benchmarks.inference --step-only "$@" 2>&1 | grep -E "^STEP|Error" | tail -3
}
if [ "$part" = all ] || [ "$part" = 1 ]; then
  timeout 200 python3 -m benchmarks.pallas_check --particles 32 2>&1 | grep -E "PALLAS|Error" \
    | tail -3
  for b in 32 64 128; do step --reps 20 --backend pallas --block "$b"; done
fi
if [ "$part" = all ] || [ "$part" = 2 ]; then
  step --reps 10 --backend pallas --accurate
  timeout 220 python3 -m benchmarks.pallas_check --particles 32 2>&1 | grep -vE "^\s*$" | tail -12
fi
if [ "$part" = all ] || [ "$part" = 3 ]; then
  timeout 100 python3 -m benchmarks.gradient_cost --backend fused --no-write --reps 5 2>&1 | tail -7
  step --reps 3 --backend fused --accurate
  timeout 150 python3 -m benchmarks.gradient_cost --backend pallas --tangent-layout rows \
    --no-write --reps 5 2>&1 | tail -7
fi
