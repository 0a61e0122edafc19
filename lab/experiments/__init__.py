"""TocabiLab's experiments 2 and 3 (docs/experiments.md): the gait comparison (``python -m
lab.experiments.compare_gaits``) and the obstacle test (``python -m lab.experiments.obstacle_test``), with their
recorded rollouts (:mod:`.gait_record`), the obstacle analysis (:mod:`.obstacle_eval`) and what both share
(:mod:`.common`)."""
