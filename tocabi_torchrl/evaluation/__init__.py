"""The gait tests of a walking policy and their metrics (docs/evaluation.md): the standard test
(:mod:`.gait_test`: 256 robots at (0.5, 0) m/s for 8 s, ``GAIT_CRITERIA``), the robust test (:mod:`.robust`:
randomised cases, ``ROBUST_CRITERIA``), the per-robot accounting and checkpoint loading they share (:mod:`.record`),
and their figures (:mod:`.plots`) and video (:mod:`.video`). ``recipes/play.py`` and ``recipes/ppo_walk.py`` run
them."""

from .._lazy import lazy_names

__all__ = [
    "GAIT_CRITERIA",
    "ROBUST_CRITERIA",
    "evaluate_policy",
    "evaluate_run",
    "eval_out_dir",
    "gait_passes",
    "gait_report_text",
    "RobustTestConfig",
    "evaluate_robust_run",
    "robust_passes",
    "robust_report_text",
    "GaitMetrics",
    "load_policy",
    "OutputExistsError",
]

# Each name loads its submodule when first read: the gait test's modules load torch, torchrl and mujoco.
__getattr__, __dir__ = lazy_names(globals(), {
    "gait_test": ("GAIT_CRITERIA", "ROBUST_CRITERIA", "evaluate_policy", "evaluate_run", "eval_out_dir",
                  "gait_passes", "gait_report_text"),
    "robust": ("RobustTestConfig", "evaluate_robust_run", "robust_passes", "robust_report_text"),
    "record": ("GaitMetrics", "load_policy"),
    "output": ("OutputExistsError",),
})
