"""The per-library table (docs/adapters_table.md): each RL library's training rate and time to walk on the walking
task, run as ``python -m lab.library_table`` from the repository root (:mod:`.table`)."""
