"""The project's laboratory, beside the package and not installed with it: benchmarks (``lab.benchmarks``), the
TocabiLab experiments (``lab.experiments``), the per-library table (``lab.library_table``) and the simulator
measurements that chose its settings (``lab.sim_measure``). Run its tools from the repository root
(``python -m lab.benchmarks.env_throughput``). It imports ``tocabi_torchrl``; ``tocabi_torchrl`` never imports it
(tests/test_layering.py)."""
