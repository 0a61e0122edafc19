"""Measurements of the simulator that chose its settings: the constraint buffer sizes (:mod:`.measure_buffers`,
``python -m lab.sim_measure.measure_buffers``) and C MuJoCo vs mujoco-warp divergence (:mod:`.parity`)."""
