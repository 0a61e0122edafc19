"""What each :class:`~tocabi_torchrl.rl.config.PPOConfig` field means on the command line, and which fields a resumed
run may change. ``recipes/ppo_walk.py --help`` is built from :data:`FIELD_HELP` (with the allowed values of
``PPOConfig.field_choices``), and ``--resume`` refuses changes to any field outside :data:`RESUME_SAFE`.
"""

from __future__ import annotations

__all__ = ["FIELD_HELP", "RESUME_SAFE", "field_help"]

#: One line per PPOConfig field: what it sets and its unit. Allowed values and defaults are appended by the parser.
FIELD_HELP: dict[str, str] = {
    "preset": "named configuration the other options start from",
    "name": "run folder name under run_dir; an existing run is never overwritten (--resume it or pick a new name)",
    "run_dir": "parent folder of the run folders",
    "seed": "seed of torch and of the env's random draws",
    "device": "auto (CUDA if present, else the small CPU smoke run), cpu, cuda or cuda:N",
    "num_envs": "parallel simulated robots",
    "control_mode": "what the 12 leg actions command",
    "command_preset": "velocity-command schedule of the episodes",
    "transform_preset": "observation history layout",
    "max_episode_steps": "policy steps (4 ms) before an episode is truncated",
    "pd_gains": "leg servo gains of the PD modes: TocabiLab's (Kp/9, Kv/3) or the robot's",
    "pd_action_scale": "residual range of the PD modes [rad]: target = center + scale × action",
    "torque_assist": "torque mode training aid: start scale β in [0, 1] of the morph from PD residuals (β = 1) to "
                     "torques (β = 0); 0 = off",
    "assist_fade_start": "env steps at which the torque assist starts to fade",
    "assist_fade_end": "env steps at which the torque assist reaches 0 (pure torque from there on)",
    "assist_absorb": "weight of the loss that moves each step of the morph into the actor",
    "assist_target": "what that loss copies: 'teacher' (the torque of a frozen copy of the actor taken as the fade "
                     "starts, DAgger) or 'rollout' (the torque the rollout's own mean applied)",
    "assist_anchor_decay": "env steps after assist_fade_end over which the teacher's pull falls to 0",
    "reward_weights": "reward re-weighting as term=weight entries; empty = the reference weights",
    "cuda_graph": "capture the env step as one CUDA graph (auto: up to 128 envs)",
    "store_env_signals": "keep every env signal in the rollout (more memory; off keeps what PPO reads)",
    "steps_per_env": "rollout length per env and iteration [policy steps]",
    "total_env_steps": "training budget in env steps (all envs together)",
    "max_minutes": "wall-clock budget [min]; 0 = none",
    "epochs": "passes over each rollout per update",
    "minibatch_size": "frames per mini-batch",
    "gamma": "discount factor per policy step",
    "gae_lambda": "GAE lambda",
    "clip_epsilon": "PPO ratio clip",
    "entropy_coef": "entropy bonus weight; 0 = none",
    "value_coef": "value loss weight",
    "value_loss": "value loss function",
    "max_grad_norm": "gradient norm clip",
    "update_graph": "on a GPU, capture each mini-batch step as a CUDA graph",
    "lr": "learning rate (start value of the schedule)",
    "lr_end": "final learning rate of the linear schedule",
    "lr_schedule": "learning-rate schedule (adaptive: from the KL to desired_kl)",
    "desired_kl": "KL target of the adaptive schedule",
    "value_head_lr": "constant learning rate of the value head; 0 = share the policy's",
    "adam_eps": "Adam epsilon",
    "actor_hidden": "hidden layer sizes of the policy network",
    "critic_hidden": "hidden layer sizes of the value network",
    "activation": "hidden-layer activation",
    "value_out_gain": "init gain of the value output layer",
    "std_mode": "action noise: scheduled (std_start -> std_end) or learned",
    "std_start": "action std at the start",
    "std_end": "action std at the end of the schedule",
    "std_hold": "fraction of training still left when the scheduled std reaches std_end (held there after)",
    "log_every": "iterations between log rows",
    "checkpoint_every": "iterations between checkpoints",
    "checkpoint_keep_last": "newest checkpoints kept; 0 = keep all",
    "checkpoint_keep_every": "also keep checkpoints of iterations that are multiples of this; 0 = none",
    "checkpoint_minutes": "also save checkpoints/wall_XXXXXs.pt every this many minutes of training; 0 = none",
    "loggers": "where metrics go besides the progress bar",
    "resume": "run folder or checkpoint to continue; its saved options apply, only budget/logging/eval/device "
              "options may be changed",
    "eval_at_end": "run the gait test (eval/) when training ends",
    "eval_envs": "robots in the gait test",
    "eval_seconds": "duration of the gait test [s]",
    "progress_bar": "show a progress bar (else one line per log row)",
}

#: Fields a ``--resume`` may change: they set the budget, logging, checkpoints, evaluation, where it runs, or how
#: the same computation is executed (graphs, stored signals). Every other field must equal the saved run's.
RESUME_SAFE = frozenset({
    "name", "run_dir", "device", "resume",
    "total_env_steps", "max_minutes", "lr_end",
    "log_every", "loggers", "progress_bar",
    "checkpoint_every", "checkpoint_keep_last", "checkpoint_keep_every", "checkpoint_minutes",
    "eval_at_end", "eval_envs", "eval_seconds",
    "cuda_graph", "update_graph", "store_env_signals",
})


def field_help(name: str) -> str:
    """The one-line description of ``name`` (a field added without one still gets a line naming it)."""
    return FIELD_HELP.get(name, name.replace("_", " "))
