#!/usr/bin/env bash
# Runs on the GPU machine from the repo root: GPU tests, then the throughput benchmarks (results under docs/).
# Usage: bash benchmarks/gpu_suite.sh [tests|sim|env|train|graph|profile|all]...   Logs go to $OUT (or /tmp) as well.
# graph: training throughput with the env step captured as one CUDA graph at every count (the default "auto" captures
# it up to 128 envs only, where it wins: docs/benchmarks/env_graph.md).
set -uo pipefail
log=${OUT:-/tmp}
export PYTHONUNBUFFERED=1
for part in "${@:-all}"; do
  case $part in
    tests|all) python3 -m pytest -q -m gpu -p no:cacheprovider -W ignore::DeprecationWarning tests 2>&1 | tee "$log/gpu_tests.log" | tail -25 ;;&
    sim|all) python3 benchmarks/sim_throughput.py --nworld 1024 4096 16384 --steps 200 2>&1 | tee "$log/sim.log" | grep -v "^Module" | tail -15 ;;&
    env|all) python3 benchmarks/env_throughput.py --num_envs 1024 4096 16384 --steps 200 2>&1 | tee "$log/env.log" | grep -v "^Module" | tail -12 ;;&
    train|all) python3 benchmarks/train_throughput.py --num_envs 4096 16384 --iterations 10 2>&1 | tee "$log/train.log" | grep -v "^Module" | tail -8 ;;&
    profile) python3 benchmarks/profile_train.py --num_envs 4096 --out "$log/profile" 2>&1 | tee "$log/profile.log" | grep -v "^Module" | tail -16 ;;&
    graph) python3 benchmarks/train_throughput.py --num_envs 4096 16384 --iterations 10 --set cuda_graph=on --name train_throughput_graph 2>&1 | tee "$log/graph.log" | grep -v "^Module" | tail -8 ;;
  esac
done
