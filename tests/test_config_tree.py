"""The run config tree: every preset resolves to the values it had before the tree (frozen in
tests/data/presets_before_config_tree.json from the flat PPOConfig, ``build_env``'s env settings and transform
options), env and recipe share their defaults, the command line is generated from the tree, and old flat configs
migrate."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest

from tocabi_torchrl import robot
from tocabi_torchrl.config import (
    LEGACY_VALUES,
    PRESETS,
    ConfigError,
    PPOConfig,
    RunConfig,
    config_from_dict,
    preset_config,
    preset_now,
    preset_tree,
)
from tocabi_torchrl.envs import TocabiWalkConfig
from tocabi_torchrl.envs.config import ENV_FLAT_PATHS, TaskConfig
from tocabi_torchrl.rl.config import parse_args
from tocabi_torchrl.rl.trainer import env_config
from tocabi_torchrl.transforms import HISTORIES
from tocabi_torchrl.transforms import TransformSettings
from tocabi_torchrl.tree import get_path, to_dict

FROZEN = json.loads((Path(__file__).parent / "data" / "presets_before_config_tree.json").read_text())
ASSETS = Path(__file__).resolve().parents[1] / "assets" / "policies"


def _plain(value):
    return json.loads(json.dumps(value, default=str))


#: The frozen presets' flat keys (the PPOConfig of before the tree) -> their path in the tree, for comparing; the
#: package itself no longer reads flat names. ``command_preset``/``pd_gains`` named values and are compared as such.
FROZEN_PATHS = {
    **{name: name for name in ("preset", "name", "run_dir", "seed", "device", "resume", "total_env_steps",
                               "max_minutes", "log_every", "loggers", "progress_bar", "checkpoint_every",
                               "checkpoint_keep_last", "checkpoint_keep_every", "checkpoint_minutes", "eval_at_end",
                               "eval_envs", "eval_seconds")},
    **{f.name: f"ppo.{f.name}" for f in dataclasses.fields(PPOConfig)},
    "num_envs": "env.num_envs", "control_mode": "env.control.mode", "max_episode_steps": "env.task.max_episode_steps",
    "pd_action_scale": "env.control.pd_action_scale", "transform_preset": "transforms.history",
}

#: Presets added after the tree, so without a flat config of before it to match (their own tests build them).
ADDED_AFTER_THE_TREE = {"model_based", "model_based_ideal", "pd", "robust", "torque"}
#: Frozen presets renamed since: the name then -> the name now (the perfect-robot torque recipe, once "torque").
RENAMED = {"torque": "torque_ideal"}


def test_every_preset_is_frozen():
    assert set(PRESETS) == {RENAMED.get(name, name) for name in FROZEN} | ADDED_AFTER_THE_TREE


@pytest.mark.parametrize("name", sorted(FROZEN))
def test_preset_matches_the_flat_config_it_replaces(name):
    tree = preset_config(RENAMED.get(name, name))
    for key, value in FROZEN[name]["flat"].items():
        if key == "preset":
            assert tree.preset == RENAMED.get(value, value), key
        elif key == "command_preset":
            from tocabi_torchrl.envs import CommandConfig

            assert tree.env.command == CommandConfig.named(value), key
        elif key == "pd_gains":
            kp = robot.LEG_KP if value == "robot" else robot.LEG_KP / 9.0
            assert tree.env.control.pd_kp == pytest.approx(tuple(kp)), key
        elif key == "reward_weights":  # "term=weight" entries then, one weight per term now
            weights = {k: float(v) for k, v in (entry.split("=") for entry in value)}
            assert tree.transforms.reward_weight_map() == weights, key
        else:
            assert _plain(get_path(tree, FROZEN_PATHS[key])) == _plain(value), key
    # The flat dict itself is no longer read: a file holding it is refused, saying what it is.
    with pytest.raises(ConfigError, match=r"flat PPOConfig of before the run config tree"):
        config_from_dict(FROZEN[name]["flat"])


@pytest.mark.parametrize("training", [False, True], ids=["eval_env", "training_env"])
@pytest.mark.parametrize("name", sorted(FROZEN))
def test_preset_builds_the_env_and_transforms_it_built_before(name, training):
    frozen = FROZEN[name]["training_env" if training else "env"]
    cfg = preset_config(RENAMED.get(name, name))
    env = env_config(cfg, for_training=training)
    assert env.num_envs == frozen["num_envs"] and cfg.seed == frozen["seed"]
    pd_acts = env.control.mode != "torque" or env.control.torque_assist
    for key, value in frozen["task"].items():
        if key in ("pd_kp", "pd_kv", "pd_action_scale") and not pd_acts:
            continue  # no PD acts in plain torque mode: the old env kept Kp/9 there, unused
        path = "command" if key == "command" else ENV_FLAT_PATHS[key]
        got = get_path(env, path)
        got = to_dict(got) if dataclasses.is_dataclass(got) else got
        assert _plain(got) == pytest.approx(_plain(value)) if key in ("pd_kp", "pd_kv") else _plain(got) == _plain(value), key
    tf = cfg.transforms.transform_config()
    frozen_tf = frozen["transforms"]
    assert HISTORIES[cfg.transforms.history].history == tf.history
    assert cfg.transforms.history == frozen_tf["history"]
    assert dict(tf.reward_weights) == frozen_tf["reward_weights"]
    for key in ("normalization", "zero_reward_on_terminated", "compile_reward", "phase_harmonics", "obs_clip",
                "track_episode_return"):
        assert getattr(tf, key) == frozen_tf[key], key
    # One truncation clock: the env's episode length is the old StepCounter's, and the StepCounter only counts.
    assert env.task.max_episode_steps == frozen_tf["max_episode_steps"] and tf.max_episode_steps is None


def test_env_and_recipe_share_their_defaults():
    default = preset_tree("default")
    assert TocabiWalkConfig() == default.env and TransformSettings() == default.transforms
    assert RunConfig() == dataclasses.replace(default, preset="default")


def test_command_line_sets_nested_options_over_the_preset(capsys):
    cfg, given = parse_args(["--preset", "cpu_smoke", "--ppo.lr", "3e-4", "--env.num_envs", "4",
                             "--env.control.mode", "torque", "--env.command.vx_range", "0.1", "0.3",
                             "--ppo.minibatch_size", "16", "--env.task.motion", "None",
                             "--transforms.reward_weights.qpos", "0.5", "--ppo.actor_hidden", "32", "16"])
    assert (cfg.ppo.lr, cfg.env.num_envs, cfg.env.control.mode) == (3e-4, 4, "torque")
    assert cfg.env.command.vx_range == (0.1, 0.3) and cfg.env.task.motion is None
    assert cfg.transforms.reward_weight_map() == {"qpos": 0.5, "body_vel": 0.9} and cfg.ppo.actor_hidden == (32, 16)
    assert cfg.preset == "cpu_smoke" and cfg.ppo.epochs == preset_config("cpu_smoke").ppo.epochs  # the preset's
    assert given["env.num_envs"] == 4 and "ppo.epochs" not in given
    # The flat options of before the tree are gone.
    for argv in (["--num_envs", "4"], ["--lr", "3e-4"], ["--command_preset", "reference"]):
        with pytest.raises(SystemExit):
            parse_args(argv)
        assert f"Unrecognized options: {argv[0]}" in " ".join(capsys.readouterr().err.replace("│", " ").split())


def test_bad_options_name_the_option_and_the_fix(capsys):
    with pytest.raises(ConfigError, match=r"'ppo.lrr': ppo has no 'lrr'; it has \[.*'lr'"):
        preset_config("default", **{"ppo.lrr": 1e-3})
    with pytest.raises(ValueError, match=r"env.control.mode"):
        preset_config("default", **{"env.control.mode": "position"})
    with pytest.raises(ValueError, match=r"ppo.torque_assist > 0 needs control_mode='torque' \(env.control.mode\)"):
        preset_config("default", **{"ppo.torque_assist": 0.5, "ppo.assist_fade_end": 10})
    # A preset's mini-batch with a CPU's few envs: the message gives a size that fits, and that size works.
    with pytest.raises(ValueError, match=r"exceeds the rollout \(8 envs × 48 steps = 384\).*ppo.minibatch_size=96: "):
        preset_config("torque_ideal", **{"env.num_envs": 8})
    assert preset_config("torque_ideal", **{"env.num_envs": 8, "ppo.minibatch_size": 96}).ppo.minibatch_size == 96
    with pytest.raises(ValueError, match=r"checkpoint_minutes 0.01 is a snapshot period of 0.6 s"):
        preset_config("default", checkpoint_minutes=0.01)  # wall_XXXXXs names are whole seconds
    assert preset_config("default", checkpoint_minutes=1 / 60).checkpoint_minutes == 1 / 60
    with pytest.raises(SystemExit):
        parse_args(["--ppo.epochs", "three"])
    err = capsys.readouterr().err
    assert "--ppo.epochs" in err and "'three'" in err
    with pytest.raises(ConfigError, match=r"unknown config option\(s\) \['ppo.warp'\]"):
        config_from_dict({"ppo": {"warp": 1}})
    with pytest.raises(ConfigError, match=r"section 'env' must be a TocabiWalkConfig .* e.g. 'env.num_envs'"):
        preset_config("default", env=5)
    with pytest.raises(ConfigError, match=r"did you mean \['ppo.gamma'\]"):
        preset_config("default", gama=0.9)
    with pytest.raises(ConfigError, match=r"did you mean \['env.num_envs'\]"):
        preset_config("default", num_envs=8)  # the flat names of before the tree are gone
    # A switch set from text is truthy in Python: refused by its path, in the run config and in the env's own.
    for path in ("env.task.terminate_on_self_collision", "eval_at_end", "ppo.update_graph", "transforms.compile_reward"):
        with pytest.raises(ValueError, match=rf"{path} must be True or False, got 'no'"):
            preset_config("default", **{path: "no"})
    with pytest.raises(ValueError, match=r"env.task.terminate_on_forbidden_contact must be True or False, got 0"):
        TocabiWalkConfig(task=TaskConfig(terminate_on_forbidden_contact=0)).validate()
    from tocabi_torchrl.transforms import transform_config

    with pytest.raises(ValueError, match=r"zero_reward_on_terminated must be True or False, got 'no'"):
        transform_config("reference", zero_reward_on_terminated="no")  # what make_env(...) passes its options to
    assert transform_config("reference", compile_reward=np.bool_(True)).compile_reward is True
    cfg = preset_config("default", eval_at_end=np.bool_(False))  # a numpy sweep's value, kept as a plain bool
    assert cfg.eval_at_end is False and json.loads(json.dumps(cfg.to_dict()))["eval_at_end"] is False


@pytest.mark.parametrize("loggers", [None, 5])
def test_loggers_that_are_no_tuple_of_names_are_refused_by_name(loggers):
    # set(None) failed as a raw "'NoneType' object is not iterable" TypeError (a saved config's null, too).
    with pytest.raises(ValueError, match=rf"loggers must be a tuple of names from \('csv', 'tensorboard', 'wandb'\) "
                                         rf"\(csv is always written; \(\) for no others\), got {loggers!r}"):
        preset_config("default", loggers=loggers)
    saved = {**RunConfig().to_dict(), "loggers": loggers}
    with pytest.raises(ValueError, match="loggers must be a tuple of names"):
        config_from_dict(saved).validate()


def test_tree_round_trips_through_json():
    cfg = preset_config("torque_ideal")
    assert config_from_dict(json.loads(json.dumps(cfg.to_dict()))) == cfg


@pytest.mark.parametrize("policy", ["tocabi_walk_ppo.pt", "tocabi_walk_torque.pt", "tocabi_walk_model_based.pt"])
def test_shipped_policies_hold_the_current_tree(policy):
    path = ASSETS / policy
    if not path.is_file():
        pytest.skip("shipped policy not present")
    from tocabi_torchrl.rl.checkpoint import SCHEMA_VERSION, config_from_checkpoint, read_checkpoint

    state = read_checkpoint(path)
    assert state["schema_version"] == SCHEMA_VERSION and "ppo" in state["config"]
    cfg = config_from_checkpoint(state, path)
    assert to_dict(cfg) == state["config"]  # every option saved, by its current name: nothing to migrate
    assert cfg.transforms.history == "reference" and cfg.transforms.reward_weight_map() == {"body_vel": 0.9}
    # Re-saved from the flat config they were trained with: that config's full reset pass, the robot's gains.
    assert cfg.env.sim.reset_pass == LEGACY_VALUES["env.sim.reset_pass"]
    if cfg.env.control.mode != "model_based":
        assert cfg.env.control.pd_kp == pytest.approx(tuple(robot.LEG_KP))


def test_the_shipped_robust_policy_was_trained_with_the_committed_robust_preset():
    # A policy "walks" only from a from-scratch run of the committed preset: a preset changed since must be re-run
    # (and the policy re-shipped), not left claiming the old run's verdict.
    path = ASSETS / "tocabi_walk_robust.pt"
    if not path.is_file():
        pytest.skip("shipped policy not present")
    from tocabi_torchrl.rl.checkpoint import config_from_checkpoint, read_checkpoint

    state = read_checkpoint(path)
    trained, preset = config_from_checkpoint(state, path), preset_config("robust")
    assert to_dict(trained) == state["config"]
    for section in ("env", "transforms", "ppo"):
        assert to_dict(getattr(trained, section)) == to_dict(getattr(preset, section)), section
    assert state["env_steps"] < trained.total_env_steps and state["train_seconds"] <= 30 * 60


@pytest.mark.parametrize("seed", [0, 1])
def test_the_torque_records_that_walk_were_trained_with_the_committed_torque_preset(seed):
    # The seed-0 run set transforms.observation on the command line before the preset did, the seed-1 run only its
    # seed: the env, transforms and PPO sections of each must be the preset's, else the record is of another recipe.
    record = Path(__file__).resolve().parents[1] / "docs" / "training" / "torque" / f"h100_base_vel_seed{seed}"
    trained, preset = config_from_dict(json.loads((record / "config.json").read_text())), preset_config("torque")
    for section in ("env", "transforms", "ppo"):
        assert to_dict(getattr(trained, section)) == to_dict(getattr(preset, section)), section
    assert trained.preset == "torque" and trained.seed == seed and preset.seed == 0
    assert preset.transforms.observation == "base_vel"


@pytest.mark.parametrize("name, record, mode", [
    ("model_based", "model_based/h100_robust_seed0", "model_based"),  # the feed-forward law is the prior
    ("pd", "pd/h100_seed0", "pd_held"),  # the robot's PD on sensed joints, held for the step
])
def test_the_records_set_over_the_robust_preset_were_trained_with_their_committed_preset(name, record, mode):
    # Each run set the preset's values on the command line over the robust preset (its saved preset is "robust"): the
    # env, transforms and PPO sections must be the preset's, else the record is of another recipe.
    folder = Path(__file__).resolve().parents[1] / "docs" / "training" / record
    trained = config_from_dict(json.loads((folder / "config.json").read_text()))
    preset = preset_config(name)
    for section in ("env", "transforms", "ppo"):
        assert to_dict(getattr(trained, section)) == to_dict(getattr(preset, section)), section
    assert trained.preset == "robust" and trained.seed == 0 and preset.seed == 0
    assert preset.env.control.mode == mode and preset.ppo.torque_assist == 0  # no torque assist
    # The pd run's KL rule acts before every mini-batch: once per iteration, the first held-PD run broke.
    assert preset.ppo.kl_adapt_every == ("minibatch" if name == "pd" else "iteration")


def test_records_of_the_model_based_preset_of_before_the_rename_read_as_model_based_ideal():
    assert preset_now("model_based", "2026-12-05") == "model_based_ideal"
    assert preset_now("model_based", "2026-12-06") == "model_based"


def test_a_tree_saved_before_the_renames_reads_by_the_new_names():
    # Checkpoints and config.json of schema 2 hold the history layout as transforms.preset and the weights as
    # "term=weight" entries: the loader's one rename step reads them.
    old = preset_tree("reference").to_dict()
    old["transforms"] = {**old["transforms"], "preset": "tocabilab", "reward_weights": ["qpos=0.5"]}
    del old["transforms"]["history"]
    cfg = config_from_dict(old)
    assert cfg.transforms.history == "tocabilab" and cfg.transforms.reward_weight_map() == {"qpos": 0.5}
    assert config_from_dict({**old, "transforms": {**old["transforms"], "reward_weights": []}}
                            ).transforms.reward_weight_map() == {}  # empty: the reference weights
    with pytest.raises(ConfigError, match=r"must look like 'body_vel=0.9'"):
        config_from_dict({**old, "transforms": {**old["transforms"], "reward_weights": ["qpos"]}})


def test_flat_names_of_before_the_tree_are_gone():
    cfg = preset_config("cpu_smoke")
    assert not hasattr(cfg, "minibatch_size") and not hasattr(cfg, "num_envs")
    with pytest.raises(ConfigError, match=r"flat PPOConfig"):
        config_from_dict({"num_envs": 8, "lr": 1e-3})


def test_option_prefixes_are_not_expanded(capsys):
    # --total used to set total_env_steps and --see the seed, silently; an ambiguous prefix named hidden flat flags.
    for argv in (["--total", "100"], ["--see", "7"], ["--ppo.l", "0.1"]):
        with pytest.raises(SystemExit):
            parse_args(argv)
        assert "Unrecognized options" in capsys.readouterr().err


def test_int_options_take_whole_numbers_written_as_floats(capsys):
    cfg, _ = parse_args(["--preset", "torque", "--total_env_steps", "2e8", "--ppo.assist_fade_start", "4.0e7",
                         "--env.num_envs", "4096"])
    assert cfg.total_env_steps == 200_000_000 and type(cfg.total_env_steps) is int
    assert cfg.ppo.assist_fade_start == 40_000_000 and cfg.env.num_envs == 4096
    for argv in (["--total_env_steps", "2.5e0"], ["--env.num_envs", "nan"], ["--total_env_steps", "lots"]):
        with pytest.raises(SystemExit):
            parse_args(argv)
        err = " ".join(capsys.readouterr().err.replace("│", " ").split())
        assert f"Error parsing {argv[0]}: expected" in err and "2e8" in err, err


def test_a_section_given_as_a_dict_of_some_options_keeps_the_others():
    # It was built from the class defaults: the robust preset's env.pushes={"calm_fraction": 0.25} trained with no
    # kicks (count 0), the reference's env.command dict lost its ranges.
    from tocabi_torchrl.config import preset_config

    robust = preset_config("robust")
    calm = preset_config("robust", **{"env.pushes": {"calm_fraction": 0.25}})
    assert calm.env.pushes == dataclasses.replace(robust.env.pushes, calm_fraction=0.25)
    nested = preset_config("robust", **{"env": {"pushes": {"count": 8}}})
    assert nested.env.pushes.count == 8 and nested.env.pushes.speed == robust.env.pushes.speed
    assert nested.env.dynamics == robust.env.dynamics


def test_a_config_edited_in_place_leaves_presets_and_the_lab_set_alone():
    # The robust preset put the module's TOCABI_LAB_ACTUATORS / _DYNAMICS objects (and one PushConfig) into every
    # tree it built: editing one config in place switched the next preset_config("robust") and the robust gait
    # test's randomised cases to the edited values.
    from tocabi_torchrl.evaluation.robust import robust_case_config
    from tocabi_torchrl.randomize import TOCABI_LAB_ACTUATORS, tocabi_lab

    a = preset_config("robust")
    a.env.control.actuators.delay_substeps = (0, 0)
    a.env.pushes.count = 0
    a.env.dynamics.mass_scale = (1.0, 1.0)
    b = preset_config("robust")
    assert (b.env.control.actuators.delay_substeps, b.env.pushes.count, b.env.dynamics.mass_scale) == \
        ((4, 20), 16, (0.8, 1.2))
    assert TOCABI_LAB_ACTUATORS.delay_substeps == (4, 20)
    case = robust_case_config(preset_config("torque_ideal"), 1.0)
    assert case.env.control.actuators.delay_substeps == (4, 20) and case.env.dynamics.mass_scale == (0.8, 1.2)
    reference = preset_tree("reference")
    reference.env.command.vx_range = (9.0, 9.0)
    assert preset_tree("reference").env.command.vx_range != (9.0, 9.0)
    torque = preset_config("torque_ideal")
    lab = tocabi_lab(torque)  # the copy shares no section with the tree it came from
    lab.env.task.min_pelvis_height = 0.1
    assert torque.env.task.min_pelvis_height != 0.1
    from tocabi_torchrl.transforms import CallableTerm, TransformConfig
    from tocabi_torchrl.tree import replace_paths as tree_replace_paths

    term = CallableTerm("up", lambda td, nxt: nxt["base_pos"][:, 2:3], weight=0.5)
    mine = tree_replace_paths(TransformConfig(), {"reward_terms": ("qpos", term)})
    assert mine.reward_terms[1] == term and mine.reward_terms[1].fn is term.fn  # leaves are the very objects


def test_a_saved_option_that_changes_nothing_is_read_with_a_warning_and_a_new_run_still_refuses_it():
    # A run saved before the rule with --ppo.lr_end under the adaptive schedule (or a kick speed without kicks)
    # could not be resumed any more ("breaks a rule"), though it trained exactly as without the option.
    from tocabi_torchrl.config import UnusedOptionError, preset_tree
    from tocabi_torchrl.rl.checkpoint import config_from_checkpoint
    from tocabi_torchrl.tree import replace_paths as tree_replace_paths

    unused = {"ppo.lr_end": 1e-6, "ppo.std_mode": "learned", "ppo.std_hold": 0.3, "env.pushes.speed": (0.1, 0.2)}
    state = {"config": to_dict(tree_replace_paths(preset_tree("default"), unused))}  # as an older version saved it
    with pytest.warns(UserWarning, match=r"changes nothing; it is kept as saved .*: .*ppo.lr_end"):
        cfg = config_from_checkpoint(state, "old.pt", strict=True)
    assert (cfg.ppo.lr_end, cfg.ppo.std_hold, cfg.env.pushes.speed) == (1e-6, 0.3, (0.1, 0.2))
    for path, value in (("ppo.lr_end", "1e-6"), ("env.pushes.speed", "0.1 0.2")):
        with pytest.raises(UnusedOptionError, match=f"{path} .*would change nothing"):
            parse_args([f"--{path}", *value.split()])


def test_a_saved_ppo_option_that_changes_nothing_is_read_with_a_warning_and_a_new_run_still_refuses_it():
    # PPOConfig's own "changes nothing" rules (the teacher's options under assist_target 'rollout', the assist's PD
    # or lr bound without the assist, the mirror loss without augment) stayed hard errors: a run saved before them
    # could not be resumed ("breaks a rule"), though it trained exactly as without the option.
    from tocabi_torchrl.config import UnusedOptionError
    from tocabi_torchrl.rl.checkpoint import config_from_checkpoint
    from tocabi_torchrl.tree import replace_paths as tree_replace_paths

    for preset, unused, match in (
            ("torque", {"ppo.assist_target": "rollout"}, "assist_anchor_decay > 0 is about the teacher"),
            ("torque", {"ppo.assist_target": "rollout", "ppo.assist_anchor_decay": 0, "ppo.assist_lr_hold": "pull"},
             "assist_lr_hold='pull' is about the teacher"),
            ("default", {"ppo.assist_pd_sensed": True}, "assist_pd_sensed is about the torque assist"),
            ("default", {"ppo.assist_lr_max": 1e-4}, "assist_lr_max 0.0001 bounds"),
            ("default", {"ppo.symmetry_loss": 0.1}, "symmetry_loss > 0 works with")):
        state = {"config": to_dict(tree_replace_paths(preset_tree(preset), unused))}  # as an older version saved it
        with pytest.warns(UserWarning, match=f"changes nothing; it is kept as saved .*: .*{match}"):
            cfg = config_from_checkpoint(state, "old.pt", strict=True)
        assert all(get_path(cfg, path) == value for path, value in unused.items())
        argv = ["--preset", preset]
        for path, value in unused.items():
            argv += [f"--{path}", str(value).lower() if isinstance(value, bool) else str(value)]
        with pytest.raises(UnusedOptionError, match=match):
            parse_args(argv)
    # A real inconsistency stays a hard error on resume: an equivariant actor made symmetric again.
    state = {"config": to_dict(tree_replace_paths(preset_tree("default"), {"ppo.symmetry": "equivariant",
                                                                           "ppo.symmetric_policy": True}))}
    with pytest.raises(Exception, match="symmetric already"):
        config_from_checkpoint(state, "old.pt", strict=True)


def test_options_of_a_schedule_or_std_mode_the_run_does_not_use_are_refused():
    # --ppo.lr_end 1e-6 under the default's adaptive schedule, or --ppo.std_end under a learned std, trained exactly
    # as without it, without a word.
    for path, value, switch in (("ppo.lr_end", 1e-6, "ppo.lr_schedule 'linear'"),
                                ("ppo.lr_min", 1e-4, "ppo.lr_schedule 'adaptive'"),
                                ("ppo.desired_kl", 0.02, "ppo.lr_schedule 'adaptive'")):
        with pytest.raises(ValueError, match=rf"ppo.lr_schedule is 'fixed', so {path} \(read by {switch} only\) "
                                             rf"would change nothing: set ppo.lr_schedule="):
            preset_config("default", **{"ppo.lr_schedule": "fixed", path: value})
    with pytest.raises(ValueError, match=r"ppo.lr_schedule is 'adaptive', so ppo.lr_end .* set ppo.lr_schedule=linear"):
        preset_config("default", **{"ppo.lr_end": 1e-6})
    with pytest.raises(ValueError, match=r"ppo.std_mode is 'learned', so ppo.std_end, ppo.std_hold .*scheduled"):
        preset_config("default", **{"ppo.std_mode": "learned", "ppo.std_end": 0.1, "ppo.std_hold": 0.2})
    with pytest.raises(ValueError, match=r"ppo.lr_schedule is 'linear', so ppo.assist_lr_hold"):
        preset_config("torque_ideal", **{"ppo.lr_schedule": "linear", "ppo.assist_lr_hold": "pull"})
    # Under the mode that reads them they are taken; a preset's own values stay valid under another mode.
    assert preset_config("default", **{"ppo.lr_schedule": "linear", "ppo.lr_end": 1e-6}).ppo.lr_end == 1e-6
    assert preset_config("reference", **{"ppo.lr_schedule": "adaptive", "ppo.lr": 1e-4}).ppo.lr_end == 2e-7
    assert preset_config("robust", **{"ppo.lr_schedule": "fixed"}).ppo.lr_min == 5e-5
    assert preset_config("default", **{"ppo.std_mode": "learned"}).ppo.std_end == 0.05


def test_an_optional_option_takes_none_in_any_case():
    # The help and the config's messages write it "none" (env.sim.nconmax: "none = the measured default"): tyro's
    # rule refused it for a number and read it as a motion file named "none", which failed after the banner.
    cfg, _ = parse_args(["--preset", "cpu_smoke", "--env.sim.nconmax", "none", "--env.sim.threads", "NONE",
                         "--env.task.motion", "none", "--transforms.obs_clip", "none",
                         "--transforms.reward_weights.qpos", "None"], prog="ppo_walk.py")
    assert (cfg.env.sim.nconmax, cfg.env.sim.threads, cfg.env.task.motion, cfg.transforms.obs_clip) == (None,) * 4
    assert cfg.transforms.reward_weights.qpos is None
    cfg, _ = parse_args(["--preset", "cpu_smoke", "--env.sim.nconmax", "64", "--env.task.motion", "walk.npz"])
    assert (cfg.env.sim.nconmax, cfg.env.task.motion) == (64, "walk.npz")


def test_a_tuple_joined_by_commas_is_refused_with_how_to_write_it():
    # --ppo.actor_hidden 256,256 (as the library recipes' --hidden takes it) ended in tyro's "Could not find valid
    # parse", which did not say that a tuple's values are separated by spaces.
    from tocabi_torchrl.rl.config import check_command_line

    for argv, fix in ((["--ppo.actor_hidden", "256,256"], "--ppo.actor_hidden 256 256"),
                      (["--env.command.vx_range=0.1,0.3"], "--env.command.vx_range 0.1 0.3"),
                      (["--loggers", "csv,", "tensorboard", "--ppo.lr", "1e-4"], "--loggers csv tensorboard")):
        name = fix.split()[0]
        with pytest.raises(ValueError, match=rf"^{name} takes its values separated by spaces, not commas: {fix}$"):
            parse_args(argv)
        with pytest.raises(SystemExit, match=rf"^error: {name} takes its values separated by spaces"):
            check_command_line(argv, prog="ppo_walk.py")
    # Space-separated values, and the JSON of a tuple of items, are read as before.
    cfg, _ = parse_args(["--preset", "cpu_smoke", "--ppo.actor_hidden", "32", "16",
                         "--env.scene.obstacles", '[{"pos": [1, 0]}, {"pos": [2, 0]}]'])
    assert cfg.ppo.actor_hidden == (32, 16) and len(cfg.env.scene.obstacles) == 2


def test_eval_envs_0_names_the_fix_with_and_without_the_test_at_the_end():
    # --eval_at_end false --eval_envs 0 was refused as "eval_envs must be a positive int", which gave no way out.
    with pytest.raises(ValueError, match=r"got 0; eval_at_end is false, so no test runs at the end and eval_envs is "
                                         r"not needed: leave it at the preset's value \(leave --eval_envs out\)$"):
        parse_args(["--preset", "cpu_smoke", "--eval_at_end", "false", "--eval_envs", "0"])
    with pytest.raises(ValueError, match=r"got 0; for no test at the end, set eval_at_end=false instead$"):
        parse_args(["--preset", "cpu_smoke", "--eval_envs", "0"])
    cfg, _ = parse_args(["--preset", "cpu_smoke", "--eval_at_end", "false"])
    assert cfg.eval_envs == preset_config("cpu_smoke").eval_envs


def test_a_named_value_takes_any_case_and_is_kept_as_listed(tmp_path):
    # --ppo.lr_schedule Linear was refused (the allowed names listed) while --ppo.cuda_graph OFF was taken.
    from tocabi_torchrl.config import field_choices

    cfg, given = parse_args(["--preset", "cpu_smoke", "--ppo.lr_schedule", "Linear", "--ppo.lr_end", "1e-6",
                             "--env.control.mode", "PD_Reference", "--ppo.activation", "ELU", "--eval_test", "Robust"])
    assert (cfg.ppo.lr_schedule, cfg.env.control.mode, cfg.ppo.activation, cfg.eval_test) == \
        ("linear", "pd_reference", "elu", "robust")
    assert given["ppo.lr_schedule"] == "linear"
    saved = json.loads(json.dumps(cfg.to_dict()))  # what config.json holds: the listed spelling
    assert (saved["ppo"]["lr_schedule"], saved["env"]["control"]["mode"]) == ("linear", "pd_reference")
    assert config_from_dict(saved).validated() == cfg
    # The Python API and the lab's --set read the same way; a name listed in no case is still refused.
    assert preset_config("default", **{"ppo.std_mode": "Learned"}).ppo.std_mode == "learned"
    for path, allowed in field_choices().items():
        assert len({choice.lower() for choice in allowed}) == len(allowed), path  # no two differ in case only
    with pytest.raises(ValueError, match=r"ppo.lr_schedule must be one of \('fixed', 'linear', 'adaptive'\), got "
                                         r"'Linearly'"):
        parse_args(["--ppo.lr_schedule", "Linearly"])


def test_every_option_that_takes_one_of_a_few_names_takes_any_case():
    # --env.pushes.kind Velocity and transforms.normalization=Running were refused: their names were checked by
    # their sections alone, not listed with the others the rule covers.
    from tocabi_torchrl.config import field_choices
    from tocabi_torchrl.tree import leaf_types

    cfg, _ = parse_args(["--preset", "robust", "--env.pushes.kind", "Velocity",
                         "--transforms.normalization", "Running"])
    assert (cfg.env.pushes.kind, cfg.transforms.normalization) == ("velocity", "running")
    assert preset_config("default", **{"transforms.normalization": "NONE"}).transforms.normalization == "none"
    # Every str leaf but the free-text ones (names, folders, files, devices, hosts) lists its names.
    free = {"preset", "name", "run_dir", "device", "resume", "env.task.motion", "env.task.model_path", "viewer.host"}
    named = {path for path, kind in leaf_types(RunConfig()).items() if kind is str or kind == str | None}
    assert named - free <= set(field_choices()), named - free - set(field_choices())


def test_the_env_and_the_runtime_refuse_the_same_start_velocity_stds():
    # One rule (value_rules.START_VEL_STD) for the env's start velocities and the torch-free runtime's.
    from tocabi_torchrl.envs.config import TaskConfig
    from tocabi_torchrl.runtime.randomization import StartVelocity

    for value in (-0.1, 10.5):
        with pytest.raises(ValueError, match=r"env.task.start_base_vel_std \(a std\) must be a finite number in \[0"):
            TaskConfig(start_base_vel_std=value).validate()
        with pytest.raises(ValueError, match=r"start_velocity.base_std \[m/s\] must be a finite number in \[0"):
            StartVelocity(base_std=value).validate()
    for config in (TaskConfig(start_base_vel_std=float("inf")), StartVelocity(base_std=float("nan"))):
        with pytest.raises(ValueError, match="base_std|base_vel_std"):
            config.validate()
    TaskConfig(start_base_vel_std=10.0).validate()
    StartVelocity(base_std=10.0).validate()
