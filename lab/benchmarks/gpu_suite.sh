#!/usr/bin/env bash
# GPU tests, then the throughput benchmarks (results under docs/benchmarks), from the repository root of a GPU machine.
# Usage: bash lab/benchmarks/gpu_suite.sh [tests|env|train|graph|tf32|resetpass|overlap|timeline|solver|multi|all]...   (multi: 2 GPUs, not in all)   Logs go to $LOG_DIR (default /tmp) as well.
set -uo pipefail
log=${LOG_DIR:-/tmp}
for part in "${@:-all}"; do
  case $part in
    tests|all) python3 -m pytest -q -m gpu -n 0 -p no:cacheprovider tests 2>&1 | tee "$log/gpu_tests.log" | tail -25 ;;&
    env|all) python3 -m lab.benchmarks.env_throughput --num_envs 1024 4096 16384 2>&1 | tee "$log/env.log" | tail -12 ;;&
    train|all) python3 -m lab.benchmarks.train_throughput --num_envs 4096 16384 2>&1 | tee "$log/train.log" | tail -8 ;;&
    graph) python3 -m lab.benchmarks.train_throughput --set ppo.cuda_graph=on --name train_throughput_graph 2>&1 | tail -8 ;;
    tf32) python3 -m lab.benchmarks.train_throughput --num_envs 4096 16384 --set ppo.matmul_precision=high \
            --name train_throughput_tf32 2>&1 | tee "$log/tf32.log" | tail -8 ;;
    resetpass) for pass in full reduced; do python3 -m lab.benchmarks.train_throughput --num_envs 4096 \
                 --set env.sim.reset_pass=$pass --name reset_pass_$pass 2>&1 | tee -a "$log/resetpass.log" | tail -4
               python3 -m lab.benchmarks.env_throughput --num_envs 4096 --reset_pass $pass --name env_reset_pass_$pass 2>&1 \
                 | tee -a "$log/resetpass.log" | tail -4; done ;;
    overlap) python3 -m lab.benchmarks.overlap_probe --num_envs 4096 16384 2>&1 | tee "$log/overlap.log" | tail -6 ;;
    timeline) python3 -m lab.benchmarks.step_timeline --num_envs 4096 16384 2>&1 | tee "$log/timeline.log" | tail -40
              python3 -m lab.benchmarks.step_timeline --num_envs 4096 16384 --set ppo.matmul_precision=high \
                --name step_timeline_tf32 2>&1 | tee -a "$log/timeline.log" | tail -40 ;;
    solver) python3 -m lab.benchmarks.solver_load --num_envs 4096 16384 2>&1 | tee "$log/solver.log" | tail -12 ;;
    multi) python3 -m lab.benchmarks.train_throughput --num_envs 4096 --nproc 1 2 --name multi_gpu 2>&1 \
             | tee "$log/multi.log" | tail -8
           python3 -m lab.benchmarks.train_throughput --num_envs 4096 --nproc 1 2 --set ppo.update_graph=false \
             --name multi_gpu_eager_update 2>&1 | tee -a "$log/multi.log" | tail -8
           python3 -m lab.benchmarks.train_throughput --num_envs 4096 --nproc 1 2 --set ppo.update_graph=false ppo.grad_sync=ddp \
             --name multi_gpu_ddp 2>&1 | tee -a "$log/multi.log" | tail -8
           python3 -m pytest -q -p no:cacheprovider tests/test_distributed.py -k two_gpus 2>&1 | tee -a "$log/multi.log" \
             | tail -3 ;;
  esac
done
