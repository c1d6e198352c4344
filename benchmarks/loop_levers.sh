#!/usr/bin/env bash
# Issue 15: per-iteration loop-overhead levers on the GPU, one process per variant (XLA flags are
# read once per process). Prints one "STEP {json}" line per variant; run from the repo root:
#   bash benchmarks/loop_levers.sh [extra benchmarks.inference args]
set -u
CB_ALL="FUSION,CUBLAS,CUBLASLT,CUSTOM_CALL,CUDNN,WHILE,CONDITIONAL"
run() {  # $1: XLA_FLAGS, rest: args
  local flags="$1"; shift
  echo "== XLA_FLAGS='$flags' $*"
  XLA_FLAGS="$flags" timeout 120 python3 -m benchmarks.inference --step-only --reps 20 "$@" \
    2>&1 | grep -E "^STEP|Error|error:" | tail -3
}
run "" "$@"
run "--xla_gpu_enable_command_buffer=$CB_ALL --xla_gpu_graph_min_graph_size=1" "$@"
run "" --unroll-inner full "$@"
run "" --unroll-inner full --unroll-outer 5 "$@"
run "--xla_gpu_enable_command_buffer=$CB_ALL --xla_gpu_graph_min_graph_size=1" \
  --unroll-inner full "$@"
run "--xla_gpu_enable_while_loop_double_buffering=true" "$@"
