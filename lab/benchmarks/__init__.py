"""Benchmarks of tocabi-torchrl: run each as ``python -m lab.benchmarks.<name>`` from the repository root."""

import time

#: When this process began, near enough: ``python -m lab.benchmarks.X`` imports this package first, before torch and the
#: library. A run's set-up (imports, CUDA, env and kernels, agent, collector) counts from here (train_throughput).
STARTED = time.perf_counter()
