"""Run logging through torchrl's loggers: the CSV layout a run writes and the one reader of it (with the older wide
``metrics.csv``), resume appending without lost or repeated rows, TensorBoard and W&B (offline) when installed, and
the clear error when a requested logger's package is missing."""

from __future__ import annotations

import importlib.machinery
import importlib.util
import os
import sys
import types

import pytest
from torchrl.record.loggers import CSVLogger, Logger

from tocabi_torchrl.rl import logging as run_logging
from tocabi_torchrl.rl import preset_config
from tocabi_torchrl.rl.curves import read_metrics
from tocabi_torchrl.rl.metrics_files import trim_metrics
from tocabi_torchrl.rl.trainer import train

TINY = {"device": "cpu", "env.num_envs": 2, "ppo.steps_per_env": 4, "ppo.minibatch_size": 8, "total_env_steps": 16,
        "progress_bar": False, "eval_at_end": False, "checkpoint_every": 1}


def tiny(tmp_path, **extra):
    return preset_config("cpu_smoke", **{**TINY, "run_dir": str(tmp_path), "name": "run", **extra})


def scalar_lines(run, name):
    return (run / "metrics" / "scalars" / f"{name}.csv").read_text().splitlines()


def test_a_run_logs_through_torchrl_csv_logger_and_resume_appends(tmp_path):
    train(tiny(tmp_path))
    run = tmp_path / "run"
    # torchrl's CSVLogger layout: one headerless `iteration,value` file per scalar (a '/' in the name: a folder).
    assert [line.split(",")[0] for line in scalar_lines(run, "kl")] == ["1", "2"]
    assert [line.split(",")[0] for line in scalar_lines(run, "reward_terms/qpos")] == ["1", "2"]
    first = read_metrics(run)
    assert [r["iteration"] for r in first] == ["1", "2"] and [float(r["env_steps"]) for r in first] == [8, 16]
    assert read_metrics(run / "metrics") == first  # the logger's own folder reads the same
    # Resume: the same files go on, the earlier rows untouched, none repeated.
    train(preset_config("cpu_smoke", **{**tiny(tmp_path).to_dict(), "total_env_steps": 32, "resume": str(run)}))
    rows = read_metrics(run)
    assert [r["iteration"] for r in rows] == ["1", "2", "3", "4"] and rows[:2] == first
    assert [float(r["env_steps"]) for r in rows] == [8, 16, 24, 32]
    assert len(scalar_lines(run, "kl")) == 4


def test_the_loggers_are_torchrl_loggers(tmp_path):
    loggers = run_logging.make_loggers(tmp_path, tiny(tmp_path))
    assert list(loggers) == ["csv"] and isinstance(loggers["csv"], CSVLogger)
    assert all(isinstance(logger, Logger) for logger in loggers.values())
    # csv is written even when --loggers leaves it out: the package's own tools read it.
    assert list(run_logging.make_loggers(tmp_path, tiny(tmp_path, loggers=()))) == ["csv"]
    # A name as a string was read as its letters: "unknown logger(s) ['a', 'b', 'd', ...]".
    with pytest.raises(ValueError, match="loggers must be a tuple of names, e.g. \\('tensorboard',\\)"):
        tiny(tmp_path, loggers="tensorboard")


def test_read_metrics_joins_scalar_files_and_reads_older_wide_files(tmp_path):
    scalars = tmp_path / "run" / "metrics" / "scalars"
    (scalars / "reward_terms").mkdir(parents=True)
    (scalars / "env_steps.csv").write_text("3,30.0\n4,40.0\n5,5")  # the last line cut short by a kill: not read
    (scalars / "reward_terms" / "qpos.csv").write_text("4,0.25\n")
    # An older run, resumed since: its wide file's rows come first, then the per-scalar ones.
    (tmp_path / "run" / "metrics.csv").write_text("iteration,env_steps\n1,10\n2,20\n")
    rows = read_metrics(tmp_path / "run")
    assert rows == [{"iteration": "1", "env_steps": "10"}, {"iteration": "2", "env_steps": "20"},
                    {"iteration": "3", "env_steps": "30.0", "reward_terms/qpos": ""},
                    {"iteration": "4", "env_steps": "40.0", "reward_terms/qpos": "0.25"}]
    assert read_metrics(tmp_path / "run" / "metrics.csv") == rows[:2]
    assert read_metrics(tmp_path / "nothing") == []


def test_read_metrics_leaves_out_a_wide_row_cut_short(tmp_path):
    # A wide metrics.csv cut mid-line (a killed run, a partial copy) gave its last row's cut value ("1.5e-": "could
    # not convert string to float" from the curves and run_compare) or a shortened number, read as logged.
    (tmp_path / "metrics.csv").write_text("iteration,env_steps,reward\n1,10,0.25\n2,20,1.5e-")
    assert read_metrics(tmp_path / "metrics.csv") == [{"iteration": "1", "env_steps": "10", "reward": "0.25"}]
    # Resumed after the kill: the cut line runs into the header the resumed run appended, one field too many.
    (tmp_path / "metrics.csv").write_text("iteration,env_steps,reward\n1,10,0.25\n2,2iteration,env_steps,reward\n"
                                          "2,20,0.5\n")
    assert [r["reward"] for r in read_metrics(tmp_path / "metrics.csv")] == ["0.25", "0.5"]


def test_the_curves_command_names_a_missing_path_or_a_csv_it_cannot_plot(tmp_path, capsys):
    from tocabi_torchrl.rl import curves

    (tmp_path / "m.csv").write_text("iteration,foo\n1,2\n")
    for metrics, message in ((tmp_path / "nothing", "does not exist"), (tmp_path / "m.csv", "no column 'env_steps'")):
        with pytest.raises(SystemExit):
            curves.main([str(metrics), str(tmp_path / "c.png")])
        assert message in capsys.readouterr().err
    assert not (tmp_path / "c.png").exists()
    # It replaced any file it was given (a run's eval/knees.png, the last figure), and blamed the metrics for an
    # output format it cannot write.
    (tmp_path / "m.csv").write_text("iteration,env_steps,episode_return,episode_length,reward\n"
                                    "1,10,1,5,0.1\n2,20,2,6,0.2\n")
    (tmp_path / "knees.png").write_bytes(b"the gait test's figure")
    for out, message in (("knees.png", "exists; it is not replaced: pass --overwrite"),
                         ("c.pt", "matplotlib cannot write .pt files"), (".", "is a folder")):
        with pytest.raises(SystemExit):
            curves.main([str(tmp_path / "m.csv"), str(tmp_path / out)])
        assert message in capsys.readouterr().err
    assert (tmp_path / "knees.png").read_bytes() == b"the gait test's figure"
    curves.main([str(tmp_path / "m.csv"), str(tmp_path / "knees.png"), "--overwrite"])
    assert (tmp_path / "knees.png").read_bytes().startswith(b"\x89PNG")


@pytest.fixture
def drawn_figures(monkeypatch):
    """The figures ``rl.curves`` draws in the test, in order, instead of saved."""
    from tocabi_torchrl.evaluation import plots

    figures = []
    monkeypatch.setattr(plots, "save_figure", lambda fig, path, *a, **k: figures.append(fig) or path)
    return figures


def test_the_curves_show_a_value_that_has_no_neighbour_to_draw_a_line_to(tmp_path, drawn_figures):
    # A line through one point draws nothing: a run of one logged iteration plotted three empty panels.
    from tocabi_torchrl.rl import curves

    figures = drawn_figures
    (tmp_path / "m.csv").write_text("iteration,env_steps,episode_return,episode_length,reward,reward_terms/qpos\n"
                                    "1,10,1,5,0.1,0.3\n2,20,2,6,0.2,nan\n3,30,3,7,0.3,0.2\n")
    (tmp_path / "one.csv").write_text("iteration,env_steps,episode_return,episode_length,reward\n1,10,1,5,0.1\n")
    curves.plot_curves(tmp_path / "one.csv", tmp_path / "one.png")
    curves.plot_curves(tmp_path / "m.csv", tmp_path / "m.png")
    one, gaps = ({line.get_label(): line for ax in fig.axes for line in ax.get_lines()} for fig in figures)
    for line in one.values():
        assert line.get_marker() not in ("None", "", " ", None) and list(line.get_markevery()) == [0]
    # Only the lone values get a dot; a curve stays a plain line.
    assert list(gaps["qpos"].get_markevery()) == [0, 2] and gaps["reward per step"].get_marker() == "None"


def test_trim_cuts_both_layouts_back_to_the_checkpoint(tmp_path):
    scalars = tmp_path / "metrics" / "scalars"
    scalars.mkdir(parents=True)
    (scalars / "kl.csv").write_text("1,0.1\n2,0.2\n3,0.3\n4,0.")  # 3 logged after the checkpoint, 4 cut short
    (tmp_path / "metrics.csv").write_text("iteration,kl\n1,0.1\n2,0.2\n3,0.3\n")
    assert trim_metrics(tmp_path, 2) == 3
    assert (scalars / "kl.csv").read_text() == "1,0.1\n2,0.2\n"
    assert [r["iteration"] for r in read_metrics(tmp_path)] == ["1", "2", "1", "2"]
    assert trim_metrics(tmp_path, 2) == 0


@pytest.mark.parametrize("name, install", [("tensorboard", "pip install tensorboard"),
                                           ("wandb", 'pip install -e ".[wandb]" in the repository')])
def test_a_missing_logger_package_is_refused_before_anything_is_written(tmp_path, monkeypatch, name, install):
    find_spec = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec", lambda module, *a: None if module == name else
                        find_spec(module, *a))
    cfg = tiny(tmp_path, loggers=("csv", name))
    with pytest.raises(ModuleNotFoundError, match=f"--loggers {name} needs the '{name}' package") as info:
        run_logging.RunLogger(tmp_path / "run", cfg, total_iterations=2)
    assert install in str(info.value)
    with pytest.raises(ModuleNotFoundError, match=install.replace("[", r"\[")):
        train(cfg)
    assert not (tmp_path / "run").exists()


def test_tensorboard_writes_event_files(tmp_path):
    pytest.importorskip("tensorboard")
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    logger = run_logging.RunLogger(tmp_path, tiny(tmp_path, loggers=("csv", "tensorboard")), total_iterations=2)
    logger.log(1, {"kl": 0.5, "reward_terms/qpos": 0.25})
    logger.log(2, {"kl": 0.25, "reward_terms/qpos": 0.5})
    logger.close()
    assert list((tmp_path / "tensorboard").glob("events.out.tfevents.*"))
    events = EventAccumulator(str(tmp_path / "tensorboard")).Reload()
    assert [(e.step, e.value) for e in events.Scalars("kl")] == [(1, 0.5), (2, 0.25)]
    assert [r["kl"] for r in read_metrics(tmp_path)] == ["0.5", "0.25"]


def test_a_resumed_tensorboard_run_drops_the_steps_logged_after_its_checkpoint(tmp_path):
    # A run killed at iteration 4 after its checkpoint at 2 logged 3 and 4; the resumed run logs them again. Without
    # the purge TensorBoard showed both values at each step (event files are append-only).
    pytest.importorskip("tensorboard")
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    cfg = tiny(tmp_path, loggers=("csv", "tensorboard"))
    killed = run_logging.RunLogger(tmp_path, cfg, total_iterations=4)
    for it in (1, 2, 3, 4):
        killed.log(it, {"kl": float(it)})
    killed.close()
    resumed = run_logging.RunLogger(tmp_path, cfg, total_iterations=4, start_iteration=2)
    for it in (3, 4):
        resumed.log(it, {"kl": 10.0 * it})
    resumed.close()
    assert len(list((tmp_path / "tensorboard").glob("events.out.tfevents.*"))) == 2
    events = EventAccumulator(str(tmp_path / "tensorboard")).Reload()
    assert [(e.step, e.value) for e in events.Scalars("kl")] == [(1, 1.0), (2, 2.0), (3, 30.0), (4, 40.0)]


def test_a_resume_keeps_an_edited_config_json_instead_of_writing_over_it(tmp_path, capsys):
    import json

    cfg = tiny(tmp_path)
    run_logging.RunLogger(tmp_path, cfg, total_iterations=4).close()
    written = json.loads((tmp_path / "config.json").read_text())
    safe_edit = {**written, "max_minutes": 99.0}  # a resume may change it: nothing to keep
    (tmp_path / "config.json").write_text(json.dumps(safe_edit))
    run_logging.RunLogger(tmp_path, cfg, total_iterations=4, start_iteration=2).close()
    assert not list(tmp_path.glob("config.edited*")) and "was edited" not in capsys.readouterr().out
    edited = {**written, "ppo": {**written["ppo"], "gamma": 0.5}}
    for expected in ("config.edited.json", "config.edited.1.json"):
        (tmp_path / "config.json").write_text(json.dumps(edited))
        run_logging.RunLogger(tmp_path, cfg, total_iterations=4, start_iteration=2).close()
        assert json.loads((tmp_path / expected).read_text())["ppo"]["gamma"] == 0.5
        assert json.loads((tmp_path / "config.json").read_text()) == written
        out = capsys.readouterr().out
        assert f"was edited (ppo.gamma: 0.5 (the run's: {cfg.ppo.gamma!r}))" in out and expected in out
    assert json.loads((tmp_path / "config.edited.json").read_text())["ppo"]["gamma"] == 0.5  # the first not replaced


def test_a_resume_keeps_a_config_json_an_edit_left_unreadable(tmp_path, capsys):
    # A stray comma or an option of another name made the file unreadable, and the resume wrote over it silently.
    import json

    cfg = tiny(tmp_path)
    run_logging.RunLogger(tmp_path, cfg, total_iterations=4).close()
    written = (tmp_path / "config.json").read_text()
    for expected, broken in (("config.edited.json", written.replace('"ppo": {', '"ppo": {,,', 1)),
                             ("config.edited.1.json", json.dumps({**json.loads(written), "learning_rate": 5e-4}))):
        (tmp_path / "config.json").write_text(broken)
        run_logging.RunLogger(tmp_path, cfg, total_iterations=4, start_iteration=2).close()
        assert (tmp_path / expected).read_text() == broken and (tmp_path / "config.json").read_text() == written
        out = capsys.readouterr().out
        assert "does not read as a run config (" in out and expected in out


def test_wandb_logs_offline_and_a_resume_continues_its_run(tmp_path, monkeypatch):
    pytest.importorskip("wandb")
    monkeypatch.delenv("WANDB_API_KEY", raising=False)
    monkeypatch.setenv("WANDB_SILENT", "true")
    cfg = tiny(tmp_path, loggers=("csv", "wandb"))
    logger = run_logging.RunLogger(tmp_path, cfg, total_iterations=2)
    run_id = logger.loggers["wandb"].experiment.id
    logger.log(1, {"kl": 0.5})
    logger.close()
    assert (tmp_path / "wandb_run_id").read_text().strip() == run_id
    assert list((tmp_path / "wandb").glob("offline-run-*"))
    logger = run_logging.RunLogger(tmp_path, cfg, total_iterations=2, start_iteration=1)
    assert logger.loggers["wandb"].experiment.id == run_id
    logger.log(2, {"kl": 0.25})
    logger.close()


class _StandInRun:
    """What torchrl's WandbLogger uses of a ``wandb`` run."""

    def __init__(self, **kwargs):
        self.kwargs, self.id, self.logged, self.finished = kwargs, kwargs.get("id") or "new-id", [], False
        self.config = types.SimpleNamespace(update=lambda *a, **k: None)

    def define_metric(self, *args, **kwargs):
        pass

    def log(self, payload, **kwargs):
        self.logged.append(payload)

    def finish(self):
        self.finished = True


def test_wandb_wiring_with_a_stand_in_package(tmp_path, monkeypatch):
    # Whether or not wandb is installed: how the run is opened, fed and continued.
    import torchrl.record.loggers.wandb as torchrl_wandb

    runs = []
    stand_in = types.ModuleType("wandb")
    stand_in.__spec__ = importlib.machinery.ModuleSpec("wandb", None)
    stand_in.init = lambda **kwargs: runs.append(_StandInRun(**kwargs)) or runs[-1]
    monkeypatch.setitem(sys.modules, "wandb", stand_in)
    monkeypatch.setattr(torchrl_wandb, "_has_wandb", True)
    monkeypatch.delenv("WANDB_API_KEY", raising=False)
    monkeypatch.delenv("WANDB_MODE", raising=False)
    cfg = tiny(tmp_path, loggers=("wandb",), name="walk")
    logger = run_logging.RunLogger(tmp_path, cfg, total_iterations=2)
    logger.log(1, {"kl": 0.5, "reward_terms/qpos": 0.25})
    logger.close()
    opened = runs[0].kwargs
    assert opened["mode"] == "offline" and opened["project"] == "tocabi-torchrl" and opened["name"] == "walk"
    assert opened["dir"] == str(tmp_path) and opened["config"] == cfg.to_dict() and opened["id"] is None
    assert "WANDB_MODE" not in os.environ  # offline for this run, not for the process
    # One history row per iteration, each metric group with its step (the iteration).
    assert runs[0].logged == [{"kl": 0.5, "step": 1, "reward_terms/qpos": 0.25, "reward_terms/step": 1}]
    assert runs[0].finished and (tmp_path / "wandb_run_id").read_text() == "new-id\n"
    assert [r["kl"] for r in read_metrics(tmp_path)] == ["0.5"]  # and the CSV, always
    run_logging.RunLogger(tmp_path, cfg, total_iterations=2, start_iteration=1).close()
    assert runs[1].kwargs["id"] == "new-id" and runs[1].kwargs["resume"] == "allow"


def test_the_curves_draw_the_update_where_the_run_logged_it(tmp_path, drawn_figures):
    from tocabi_torchrl.rl import curves

    figures = drawn_figures
    (tmp_path / "u.csv").write_text("iteration,env_steps,episode_return,episode_length,reward,lr,kl,clip_fraction,"
                                    "behaviour_ess\n1,10,1,5,0.1,1e-3,0.02,0.3,0.9\n2,20,2,6,0.2,5e-4,0.03,0.2,0.8\n")
    (tmp_path / "n.csv").write_text("iteration,env_steps,episode_return,episode_length,reward\n1,10,1,5,0.1\n")
    curves.plot_curves(tmp_path / "u.csv", tmp_path / "u.png")
    curves.plot_curves(tmp_path / "n.csv", tmp_path / "n.png")
    with_update, without = figures
    titles = [ax.get_title() for ax in with_update.axes]
    assert "PPO update" in titles and "PPO update" not in [ax.get_title() for ax in without.axes]
    panel = with_update.axes[titles.index("PPO update")]
    labels = {line.get_label() for ax in with_update.axes for line in ax.get_lines()}
    assert {"learning rate", "kl", "clip_fraction", "behaviour_ess"} <= labels and panel.get_yscale() == "log"
