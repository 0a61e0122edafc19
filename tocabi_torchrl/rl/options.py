"""What each option of the run config tree (:class:`~tocabi_torchrl.config.RunConfig`, by dotted path) means on the
command line, and which options a resumed run may change. ``recipes/ppo_walk.py --help`` is built from
:data:`FIELD_HELP` (with the allowed values of ``config.field_choices``), and ``--resume`` refuses changes to any
option outside :data:`RESUME_SAFE`.
"""

from __future__ import annotations

__all__ = ["FIELD_HELP", "RESUME_SAFE", "field_help", "resume_safe_text"]

#: Paths a ``--resume`` may change: they set the budget, logging, checkpoints, evaluation, where it runs, or how
#: the same computation is executed (CUDA graphs, gradient sync, stored env signals, CPU threads, reset pass), or
#: whether a live viewer watches it (viewer.*, which changes nothing of the computation). Every
#: other option must equal the saved run's: a schedule's end point (``ppo.lr_end``) is not among them, since changing
#: it mid-run makes the rate jump to another line.
RESUME_SAFE = frozenset({
    "name", "run_dir", "device", "resume",
    "total_env_steps", "max_minutes",
    "log_every", "loggers", "progress_bar",
    "checkpoint_every", "checkpoint_keep_last", "checkpoint_keep_every", "checkpoint_minutes",
    "eval_at_end", "eval_envs", "eval_seconds", "eval_test",
    "ppo.cuda_graph", "ppo.update_graph", "ppo.grad_sync", "ppo.store_env_signals",
    "env.sim.threads", "env.sim.reset_pass",
    "viewer.enabled", "viewer.host", "viewer.port", "viewer.worlds", "viewer.every",
})


def resume_safe_text() -> str:
    """The options a ``--resume`` may give other values (:data:`RESUME_SAFE` but ``resume``), as ``--help`` and the
    refusal of a changed option list them."""
    return ", ".join(sorted(RESUME_SAFE - {"resume"}))


#: One line per leaf of the run config tree (by path): what it sets and its unit. Allowed values and defaults are appended by the parser.
FIELD_HELP: dict[str, str] = {
    "preset": "named configuration the other options start from",
    "name": "run folder name under run_dir; an existing run is never overwritten (--resume it or pick a new name)",
    "run_dir": "parent folder of the run folders",
    "seed": "seed of torch and of the env's random draws, in [0, 2**63 - 1]",
    "device": "auto (CUDA if present, else the small CPU smoke run), cpu, cuda or cuda:N",
    "env.num_envs": "parallel simulated robots",
    "env.control.mode": "what the 12 leg actions command",
    "env.control.upper_body": "the upper body's control law (pd_hold: its servos hold the reference walk's pose)",
    "transforms.preset": "observation history layout",
    "env.task.max_episode_steps": "policy steps (4 ms) before an episode is truncated",
    "env.control.pd_kp": "leg PD stiffness per joint [N·m/rad] (PD modes, torque assist); default: the robot's, "
                         "TocabiLab used Kp/9",
    "env.control.pd_kv": "leg PD damping per joint [N·m·s/rad]; default: the robot's, TocabiLab used Kv/3",
    "env.control.pd_nominal": "centre of the 'pd' mode's leg targets [rad], one per leg joint",
    "env.control.torque_assist": "give every env the torque assist (the trainer sets it on its training env when "
                                 "ppo.torque_assist > 0)",
    "env.control.mb_omega": "model_based mode: natural frequency of each leg joint's computed-torque loop [rad/s] "
                            "(Kp = ω²); default: the robot's Kp at the initial pose",
    "env.control.mb_zeta": "model_based mode: damping ratio of each leg joint's loop (Kd = 2ζω)",
    "env.control.mb_residual_gain": "model_based mode: leg torque per unit of leg action [N·m], per joint; default: "
                                    "the torque limits (the model_based preset: 0.5 rad × the robot's Kp)",
    "env.control.mb_ref_window": "model_based mode: half-width of the central differences that give the reference's "
                                 "velocity and acceleration [s]",
    "env.control.actuators.delay_substeps": "torque modes: leg torque delay (low, high) in 0.5 ms physics substeps, "
                                            "drawn per world at reset; default: none",
    "env.control.actuators.motor_constant": "torque modes: motor-constant scale (low, high) of the leg torques, drawn "
                                            "per world and joint at reset; default: 1",
    "env.control.actuators.coulomb": "torque modes: Coulomb friction (low, high) [N·m] against each leg joint's "
                                     "velocity, drawn per world and joint at reset; default: none",
    "env.control.actuators.viscous": "torque modes: viscous friction (low, high) [N·m·s/rad] of each leg joint, "
                                     "drawn per world and joint at reset; default: none",
    "ppo.push_ramp": "(start, full) env steps of the pushes' curriculum: no kicks before start, full strength from "
                     "full; (0, 0): full from the start",
    "env.task.start_joint_vel_std": "std of the Gaussian joint velocities a reset world starts with [rad/s]; 0: at "
                                    "rest (the robust gait test uses 0.5)",
    "env.task.start_base_vel_std": "std of the pelvis's Gaussian linear velocity at reset, per axis [m/s]; 0: at rest "
                                   "(the robust gait test uses 0.1)",
    "env.pushes.count": "velocity kicks of the pelvis per episode; 0: none",
    "env.pushes.window": "(start, end) of episode time over which the kicks are spread, one per equal share [s]",
    "env.pushes.speed": "(low, high) velocity change of the whole robot per kick [m/s] (impulse = speed x mass)",
    "env.pushes.duration": "(low, high) how long each kick's force acts [s], in whole policy steps (at least one)",
    "env.control.actuators.saturate": "torque modes: clip the leg torques at their limits after the actuator stages",
    "env.sim.backend": "physics backend (auto: mujoco-warp on CUDA, C MuJoCo on the CPU)",
    "env.sim.substeps": "physics substeps (0.5 ms) per policy step",
    "env.sim.nconmax": "mujoco-warp contacts per world; none = the measured default",
    "env.sim.njmax": "mujoco-warp constraint rows per world; none = the measured default",
    "env.sim.threads": "CPU threads of the mujoco backend; none = every available core",
    "env.sim.reset_pass": "mujoco-warp reset: full forward pass, or reduced (position and velocity stages plus a "
                          "start-state table; the same result)",
    "env.dynamics.mass_scale": "(low, high) scale of each link's mass and inertia, drawn per world and body at every "
                               "reset; default (1, 1): off",
    "env.dynamics.joint_damping": "(low, high) damping added to each joint [N·m·s/rad], drawn per world and joint at "
                                  "every reset; default (0, 0): off",
    "env.dynamics.armature_scale": "(low, high) scale of each joint's armature, drawn per world and joint at every "
                                   "reset; default (1, 1): off",
    "env.dynamics.friction_scale": "(low, high) scale of every geom's sliding friction (so of the ground contact's), "
                                   "drawn per world at every reset; the shipped model's is 1, so (0.4, 1.0) is "
                                   "friction U(0.4, 1.0); default (1, 1): off",
    "env.task.motion": "reference motion (.npz or reference .txt); none = the shipped cycle",
    "env.task.model_path": "robot model XML; none = the shipped TOCABI",
    "env.task.phase_rate_gain": "phase clock speed-up per unit of the phase action",
    "env.task.min_pelvis_height": "episode ends below this pelvis height [m]",
    "env.task.min_neck_height": "episode ends below this neck height [m]",
    "env.task.max_neck_angle": "episode ends beyond this neck tilt [rad]",
    "env.task.terminate_on_forbidden_contact": "episode ends when a body other than the feet touches the ground or "
                                               "an obstacle",
    "env.task.terminate_on_self_collision": "episode ends on a self-collision",
    "env.scene.obstacles": 'boxes on the ground [m]: size (length, width, height), pos (x, y of the centre), jitter '
                           '(x, y half-ranges of a per-world uniform offset), e.g. \'[{"size": [0.3, 0.6, 0.012], '
                           '"pos": [0.7, 0.1025], "jitter": [0.05, 0.05]}]\'; none = no obstacles',
    "env.command.vx_range": "forward command range low,high [m/s]",
    "env.command.vx_initial_range": "forward command range of an episode's first command [m/s]",
    "env.command.vy_range": "lateral command range low,high [m/s]",
    "env.command.resample_every": "policy steps between command re-samples",
    "env.command.max_ramp_steps": "commands ramp over randint(1, this) steps; 1 = switch at once",
    "env.command.ramp_survives_reset": "a ramp in progress carries over into the next episode (the reference's quirk)",
    "transforms.normalization": "observation normalisation",
    "transforms.obs_clip": "clip of the normalised observation; none = no clip",
    "transforms.zero_reward_on_terminated": "reward and terms are 0 on a terminating step",
    "transforms.compile_reward": "torch.compile the reward terms (not with a captured env step)",
    "transforms.sensor_noise.joint_pos_bias": "half-width of the observed joint positions' bias [rad], U(±b) per "
                                              "world and joint, drawn at each reset; 0: none (TOCABI lab: π/100)",
    "transforms.sensor_noise.joint_pos_noise_std": "σ of the encoder noise on the observed joint positions, fresh "
                                                   "every step [rad]; 0: none (TOCABI lab: 0.00016/3)",
    "transforms.sensor_noise.joint_pos_noise_clip": "the joint-position noise is clipped to ±this [rad]; none: not "
                                                    "clipped (TOCABI lab: 0.00016)",
    "transforms.sensor_noise.joint_vel_noise_std": "σ of the noise on the observed joint velocities, fresh every step "
                                                   "[rad/s]; 0: none",
    "transforms.sensor_noise.joint_vel_noise_clip": "the joint-velocity noise is clipped to ±this [rad/s]; none: not "
                                                    "clipped",
    "transforms.sensor_noise.base_rpy_bias": "half-width of the IMU bias on the observed roll, pitch and yaw [rad], "
                                             "U(±b) per world and axis, drawn at each reset; 0: none (TOCABI lab: "
                                             "π/150)",
    "transforms.sensor_noise.foot_force_bias": "half-width of the foot F/T force bias [N], U(±b) per world, foot and "
                                               "axis, drawn at each reset; 0: none (TOCABI lab: 100)",
    "transforms.sensor_noise.foot_torque_bias": "half-width of the foot F/T moment bias [N·m], U(±b) per world, foot "
                                                "and axis, drawn at each reset; 0: none (TOCABI lab: 10)",
    "env.control.pd_action_scale": "residual range of the PD modes [rad]: target = center + scale × action",
    "ppo.torque_assist": "torque mode training aid: start scale β in [0, 1] of the morph from PD residuals (β = 1) to "
                     "torques (β = 0); 0 = off",
    "ppo.assist_fade_start": "env steps at which the torque assist starts to fade",
    "ppo.assist_fade_end": "env steps at which the torque assist reaches 0 (pure torque from there on)",
    "ppo.assist_absorb": "weight of the loss that moves each step of the morph into the actor",
    "ppo.assist_target": "what that loss copies: 'teacher' (the torque of a frozen copy of the actor taken as the fade "
                     "starts, DAgger) or 'rollout' (the torque the rollout's own mean applied)",
    "ppo.assist_anchor_decay": "env steps after assist_fade_end over which the teacher's pull falls to 0",
    "transforms.reward_weights": "reward re-weighting as term=weight entries; empty = the reference weights",
    "ppo.cuda_graph": "capture the env step as one CUDA graph (auto: up to 128 envs)",
    "ppo.store_env_signals": "keep every env signal in the rollout (more memory; off keeps what PPO reads)",
    "ppo.steps_per_env": "rollout length per env and iteration [policy steps]",
    "total_env_steps": "training budget in env steps (all envs together)",
    "max_minutes": "wall-clock budget [min]; 0 = none",
    "ppo.epochs": "passes over each rollout per update",
    "ppo.minibatch_size": "frames per mini-batch",
    "ppo.gamma": "discount factor per policy step",
    "ppo.gae_lambda": "GAE lambda",
    "ppo.clip_epsilon": "PPO ratio clip",
    "ppo.entropy_coef": "entropy bonus weight; 0 = none",
    "ppo.value_coef": "value loss weight",
    "ppo.value_loss": "value loss function",
    "ppo.max_grad_norm": "gradient norm clip",
    "ppo.update_graph": "on a GPU, capture each mini-batch step as a CUDA graph",
    "ppo.matmul_precision": "float32 matrix products while training: highest (float32) or high (TF32 on GPUs)",
    "ppo.grad_sync": "several ranks: average gradients with one captured all-reduce, or DDP (needs update_graph false)",
    "ppo.lr": "learning rate (start value of the schedule)",
    "ppo.lr_end": "final learning rate of the linear schedule (at most ppo.lr)",
    "ppo.lr_schedule": "learning-rate schedule (adaptive: from the KL to desired_kl)",
    "ppo.desired_kl": "KL target of the adaptive schedule",
    "ppo.value_head_lr": "constant learning rate of the value head; 0 = share the policy's",
    "ppo.adam_eps": "Adam epsilon",
    "ppo.actor_hidden": "hidden layer sizes of the policy network",
    "ppo.critic_hidden": "hidden layer sizes of the value network",
    "ppo.activation": "hidden-layer activation",
    "ppo.value_out_gain": "init gain of the value output layer",
    "ppo.std_mode": "action noise: scheduled (std_start -> std_end) or learned",
    "ppo.std_start": "action std at the start",
    "ppo.std_end": "action std at the end of the schedule (at most ppo.std_start)",
    "ppo.std_hold": "fraction of training still left when the scheduled std reaches std_end (held there after)",
    "log_every": "iterations between log rows",
    "checkpoint_every": "iterations between checkpoints",
    "checkpoint_keep_last": "newest checkpoints kept; 0 = keep all",
    "checkpoint_keep_every": "also keep checkpoints of iterations that are multiples of this; 0 = none",
    "checkpoint_minutes": "also save checkpoints/wall_XXXXXs.pt every this many minutes of training; 0 = none, "
                          "else at least 1/60 (the names are whole seconds)",
    "loggers": "where metrics go besides the progress bar; csv (runs/<name>/metrics/) is always written",
    "resume": "run folder or checkpoint to continue; its saved options apply, and only these may be given other "
              f"values: {resume_safe_text()}",
    "eval_at_end": "run the gait test (eval/) when training ends",
    "eval_envs": "robots in the gait test (per case in the robust test)",
    "eval_seconds": "duration of the gait test [s]",
    "eval_test": "which gait test runs when training ends: standard (one command) or robust (diverse starts, four "
                 "cases of eval_envs robots each; docs/evaluation.md)",
    "progress_bar": "show a progress bar (else one line per log row)",
    "viewer.enabled": "serve a live web page of a few training worlds while training (the viewer extra; "
                      "docs/viewer.md)",
    "viewer.host": "address the viewer's page is served on (127.0.0.1: this machine, via ssh -L; 0.0.0.0: all)",
    "viewer.port": "TCP port of the viewer's page",
    "viewer.worlds": "training worlds shown (the first ones; at most 64)",
    "viewer.every": "policy steps between two host copies of the shown worlds' body poses",
}

def field_help(name: str) -> str:
    """The one-line description of ``name`` (a field added without one still gets a line naming it)."""
    return FIELD_HELP.get(name, name.replace("_", " "))
