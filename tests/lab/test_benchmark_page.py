"""docs/benchmarks.md is generated from the committed reports: the page equals its regeneration, and every result
on it carries the command, date and hardware of its measurement."""

from __future__ import annotations

import importlib
import re



def _page_module():
    return importlib.import_module("lab.benchmarks.page")


def test_the_committed_page_equals_its_regeneration():
    page = _page_module()
    assert page.PAGE.read_text() == page.render(), "docs/benchmarks.md is stale: run python -m lab.benchmarks.page"


def test_every_section_states_command_date_and_hardware():
    page = _page_module()
    for section in page.SECTIONS:
        text = "\n".join(section(page.DOCS))
        assert re.search(r"command", text), f"{section.__name__}: no command"
        assert re.search(r"\b20\d\d-\d\d-\d\d\b", text), f"{section.__name__}: no date"
        assert re.search(r"H100|H200|CPU cores|GPU", text), f"{section.__name__}: no hardware"


def test_check_mode_reports_a_stale_page(tmp_path, monkeypatch, capsys):
    page = _page_module()
    monkeypatch.setattr(page, "PAGE", tmp_path / "benchmarks.md")
    (tmp_path / "benchmarks.md").write_text("# Benchmarks\n\nedited by hand\n")
    assert page.main(["--check"]) == 1 and "stale" in capsys.readouterr().out
    assert page.main([]) == 0 and page.main(["--check"]) == 0


def test_randomization_cost_splits_the_gap_into_physics_and_the_rest(tmp_path):
    """With ``--physics`` the section says what on / off would be were the rest of a training step as long as off's:
    here off's step is 10 µs of which 6 µs physics, on's physics 7 µs, so 10 / 11; pieces get their physics too."""
    import json

    page = _page_module()
    n = 1000
    physics = {name: {"ms_per_policy_step": us * n * 1e-3} for name, us in
               (("on", 7.0), ("off", 6.0), ("off+actuators", 6.5))}
    report = {"meta": {"preset": "robust", "rounds": 1, "num_envs": n, "command": "python -m x", "date": "2026-12-03",
                       "gpu": "NVIDIA H200"},
              "summary": {"on_median": 80_000.0, "off_median": 100_000.0, "on_over_off": 0.8,
                          "piece_over_off": {"actuators": 0.9}, "physics_off_over_on": 6.0 / 7.0},
              "results": [{"round": 1, "variant": "on", "train_env_steps_per_s": 80_000.0}],
              "physics": physics}
    path = tmp_path / page.RANDOMIZATION_COST
    path.parent.mkdir(parents=True)
    path.write_text(json.dumps(report))
    text = "\n".join(page.randomization_cost(tmp_path))
    assert "training runs at **0.800x**" in text and "misses the 0.95x target" in text
    assert "`actuators` alone over none: 0.900x in training, physics 0.923x" in text
    assert "off / on = **0.857**" in text and "on / off would be 0.909" in text and "remaining 0.109" in text


def test_randomization_cost_without_pieces_shows_the_last_split_and_the_averaged_rounds(tmp_path):
    """A run without ``--pieces``/``--physics`` keeps the last per-piece run on the page (its own link), and the
    averaged delay's three-round run says whether it meets the target."""
    import json

    page = _page_module()
    meta = {"preset": "robust", "rounds": 3, "num_envs": 1000, "command": "python -m latest", "date": "2026-12-04",
            "gpu": "NVIDIA H200", "seeds": [0, 1, 2]}
    latest = {"meta": meta, "summary": {"on_median": 93_000.0, "off_median": 100_000.0, "on_over_off": 0.93,
                                        "round_on_over_off": [0.92, 0.93, 0.94]},
              "results": [{"round": 1, "seed": 0, "variant": "on", "train_env_steps_per_s": 93_000.0}]}
    pieces = {"meta": {**meta, "rounds": 1, "command": "python -m pieces", "date": "2026-12-03"},
              "summary": {"on_median": 90_000.0, "off_median": 100_000.0, "on_over_off": 0.9,
                          "piece_over_off": {"actuators": 0.91}},
              "results": []}
    three = {"meta": meta, "summary": {**latest["summary"], "on_over_off": 0.951,
                                       "round_on_over_off": [0.95, 0.951, 0.96]}, "results": []}
    for rel, report in ((page.RANDOMIZATION_COST, latest), (page.RANDOMIZATION_PIECES, pieces),
                        (page.DELAY_AVERAGE_THREE_ROUNDS, three)):
        (tmp_path / rel).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / rel).write_text(json.dumps(report))
    text = "\n".join(page.randomization_cost(tmp_path))
    assert "**0.930x**" in text and "misses the 0.95x target" in text
    assert "an earlier run (2026-12-03" in text and "`python -m pieces`" in text
    assert "`actuators` alone over none: 0.910x in training" in text
    assert "0.950, 0.951, 0.960) gave **0.951x**, which meets the target" in text
    (tmp_path / page.RANDOMIZATION_PIECES).unlink()
    assert "an earlier run" not in "\n".join(page.randomization_cost(tmp_path))


def test_train_over_ceiling_joins_the_solver_load_section_with_its_targets(tmp_path):
    import json

    page = _page_module()
    assert page.train_over_ceiling(tmp_path) == []  # not measured: nothing
    rows = [{"num_envs": 4096, "train_env_steps_per_s": 150_000.0, "physics_ms_per_policy_step": 24.0,
             "ceiling_env_steps_per_s": 170_666.7, "ratio_train_over_ceiling": 0.879, "ratio_train_over_raw": 0.79,
             "update_s_last": 0.096, "iterations": 10, "env_steps": 10 * 48 * 4096, "gpus": 1},
            {"num_envs": 16384, "train_env_steps_per_s": 190_000.0, "physics_ms_per_policy_step": 82.0,
             "ceiling_env_steps_per_s": 199_804.9, "ratio_train_over_ceiling": 0.951, "ratio_train_over_raw": None}]
    (tmp_path / page.TRAIN_OVER_CEILING).parent.mkdir(parents=True)
    (tmp_path / page.TRAIN_OVER_CEILING).write_text(json.dumps(
        {"meta": {"command": "python -m x --ceiling", "date": "2026-12-05", "gpu": "NVIDIA H200"}, "results": rows}))
    text = "\n".join(page.train_over_ceiling(tmp_path))
    assert "| 4,096 | 150k | 24.00 | 171k | **0.879** | 0.9 (missed) | 0.790 |" in text
    assert "| 16,384 | 190k | 82.00 | 200k | **0.951** | 0.95 (met) | - |" in text
    assert "`python -m x --ceiling`" in text and "NVIDIA H200" in text
    # 4,096 / 150k/s = 27.31 ms a step: 24.00 physics, 96 ms / 48 steps = 2.00 update, 1.31 the rest; the row without
    # an update time has no split.
    assert "| 4,096 | 27.31 | 24.00 | 2.00 | 1.31 |" in text and "| 16,384 | 86.23 |" not in text
    assert "host time from the rollout's end" in text
    # A result that timed the update itself (CUDA events around it): its GPU time, and the label says so.
    rows[0]["update_ms_last"] = 48.0  # 1.00 ms a policy step
    (tmp_path / page.TRAIN_OVER_CEILING).write_text(json.dumps(
        {"meta": {"command": "python -m x --ceiling", "date": "2026-12-07", "gpu": "NVIDIA H200"}, "results": rows}))
    text = "\n".join(page.train_over_ceiling(tmp_path))
    assert "| 4,096 | 27.31 | 24.00 | 1.00 | 2.31 |" in text and "GPU time (CUDA events around it)" in text
    assert "With options that no preset uses yet" not in text  # no variant report: no line
    # A variant report per env count, read in env-count order (16384 after 4096, not before it as text).
    variant = tmp_path / page.TRAIN_OVER_CEILING_OVERLAP
    variant.mkdir(parents=True)
    (variant / "envs4096_notes.json").write_text("not a report")  # not envs<N>.json: not read
    for n, ratio in ((16384, 0.951), (4096, 0.891), (1024, None)):
        row = {**rows[0], "num_envs": n, "ratio_train_over_ceiling": ratio,
               "overrides": {"ppo.overlap_update": True, "ppo.matmul_precision": "high"}}
        (variant / f"envs{n}.json").write_text(json.dumps(
            {"meta": {"command": "c", "date": "2026-12-05", "gpu": "NVIDIA H200"}, "results": [row]}))
    lines = [line for line in page.train_over_ceiling(tmp_path) if line.startswith("- 4,096 envs with") or
             line.startswith("- 16,384 envs with")]
    assert len(lines) == 2 and lines[0].startswith("- 4,096")
    assert not any(line.startswith("- 1,024") for line in page.train_over_ceiling(tmp_path))  # no training rate and lines[1].startswith("- 16,384")
    assert "`ppo.overlap_update=true` `ppo.matmul_precision=high`: **0.891**" in lines[0]
    assert "misses the target 0.9" in lines[0] and "meets the target 0.95" in lines[1]


def test_the_capped_solver_cost_appears_only_once_measured(tmp_path):
    import json

    page = _page_module()
    assert page.solver_cap_cost(tmp_path) == []
    meta = {"preset": "robust", "rounds": 3, "num_envs": 4096, "command": "python -m x", "date": "2026-12-04",
            "gpu": "NVIDIA H200", "seeds": [0, 1, 2]}
    summary = {"on_median": 136_000.0, "off_median": 141_000.0, "on_over_off": 0.966,
               "round_on_over_off": [0.964, 0.968, 0.966]}
    (tmp_path / page.SOLVER_CAP_THREE_ROUNDS).parent.mkdir(parents=True)
    (tmp_path / page.SOLVER_CAP_THREE_ROUNDS).write_text(json.dumps({"meta": meta, "summary": summary, "results": []}))
    text = "\n".join(page.solver_cap_cost(tmp_path))
    assert "(seeds 0, 1, 2: 0.964, 0.968, 0.966) gave **0.966x**, on 136k against off 141k" in text
    assert "2026-12-04, NVIDIA H200" in text
    assert "The capped preset's from-scratch run" not in text
    # A committed run of the capped preset: its verdict at the marks its record holds.
    run = tmp_path / page.SOLVER_CAP_RUNS[0]
    run.parent.mkdir(parents=True)
    record = {"name": "robust_v12", "gpu": "NVIDIA H200", "train_seconds": 1085.0, "time_to_walk": None,
              "evaluations": {"wall_01020s": {"train_seconds": 1021.0}, "wall_00960s": {"train_seconds": 961.0}}}
    run.write_text(json.dumps({"records": [record]}))
    text = "\n".join(page.solver_cap_cost(tmp_path))
    assert ("`robust_v12` (NVIDIA H200) does not pass at the marks in its record (16, 17 training minutes, of "
            "18.1)") in text
    # Half-minute marks read as such, by the checkpoint's name, not rounded from train_seconds (run past the mark).
    half = {"wall_00750s": {"train_seconds": 751.2}, "wall_00780s": {"train_seconds": 781.0}}
    run.write_text(json.dumps({"records": [{**record, "evaluations": half}]}))
    assert "(12.5, 13 training minutes, of 18.1)" in "\n".join(page.solver_cap_cost(tmp_path))
    run.write_text(json.dumps({"records": [{**record, "evaluations": {}}]}))
    assert "has no tested mark in its record (18.1 training minutes)" in "\n".join(page.solver_cap_cost(tmp_path))
    record["time_to_walk"] = {"train_minutes": 16.02}
    run.write_text(json.dumps({"records": [record]}))
    assert "`robust_v12` (NVIDIA H200) passes at 16.0 training minutes" in "\n".join(page.solver_cap_cost(tmp_path))
    # Overrides besides the cap itself are named, so a run with an extra lever is not read as the plain capped preset.
    record["overrides"] = {"env.sim.solver_iterations": 4, "ppo.assist_lr_max": 7.5e-05}
    run.write_text(json.dumps({"records": [record]}))
    assert "`robust_v12` (NVIDIA H200; also `ppo.assist_lr_max=7.5e-05`) passes" in "\n".join(
        page.solver_cap_cost(tmp_path))
    record["overrides"] = {"env.sim.solver_iterations": 4}
    run.write_text(json.dumps({"records": [record]}))
    assert "also" not in "\n".join(page.solver_cap_cost(tmp_path)).split("`robust_v12`")[1]


def test_the_16k_env_costs_appear_only_once_measured(tmp_path):
    import json

    page = _page_module()
    assert page.envs_16k_cost(tmp_path) == []
    meta = {"preset": "robust", "rounds": 2, "num_envs": 16384, "command": "python -m x", "date": "2026-12-05",
            "gpu": "NVIDIA H100 80GB HBM3", "seeds": [0, 1]}
    summary = {"on_median": 155_000.0, "off_median": 158_000.0, "on_over_off": 0.981,
               "round_on_over_off": [0.978, 0.984]}
    grid = tmp_path / page.ENVS_16K_REPORTS[1][0]
    grid.parent.mkdir(parents=True)
    grid.write_text(json.dumps({"meta": meta, "summary": summary, "results": []}))
    lines = page.envs_16k_cost(tmp_path)
    assert len([line for line in lines if line.startswith("- At 16,384 envs")]) == 1  # the other is not committed
    assert "1 ms grid (`env.control.actuators.delay_stride=2`): **0.981x** (2 rounds, seeds 0, 1: 0.978, 0.984" in (
        lines[0])
    assert "The preset takes the last row's settings" in lines[1] and page.PRESET_RUN in lines[1]


def test_the_committed_presets_cost_leads_once_measured(tmp_path):
    import json

    page = _page_module()
    assert page.preset_cost(tmp_path) == []
    meta = {"preset": "robust", "rounds": 2, "num_envs": 16384, "command": "python -m x --num_envs 16384",
            "date": "2026-12-06", "gpu": "NVIDIA H200", "seeds": [0, 1]}
    summary = {"on_median": 160_348.0, "off_median": 163_523.0, "on_over_off": 0.981,
               "round_on_over_off": [0.977, 0.985]}
    report = tmp_path / page.PRESET_COST
    report.parent.mkdir(parents=True)
    report.write_text(json.dumps({"meta": meta, "summary": summary, "results": []}))
    text = "\n".join(page.preset_cost(tmp_path))
    assert "committed `robust` preset on" in text and "16,384 envs), training runs at **0.981x**" in text
    assert "0.977, 0.985; on 160k against off 164k" in text and "this meets the 0.95x target" in text
    assert "- command: `python -m x --num_envs 16384`" in text and "hardware: NVIDIA H200" in text
    summary["on_over_off"] = 0.94
    report.write_text(json.dumps({"meta": meta, "summary": summary, "results": []}))
    assert "this misses the 0.95x target" in "\n".join(page.preset_cost(tmp_path))


def test_docstring_examples_run():
    import doctest

    result = doctest.testmod(_page_module())
    assert result.attempted >= 1 and result.failed == 0


def test_a_report_without_a_field_the_page_shows_is_named_not_a_key_error(tmp_path, monkeypatch, capsys):
    """A time_to_walk report of runs whose train.json has no date (older runs) or no raw ceiling (``--raw_steps 0``)
    once ended the page with ``KeyError: 'date'``; any other report without a field the page shows, likewise."""
    import json
    import shutil

    import pytest

    page = _page_module()
    for report in page.RUN_TIME_TO_WALK:  # the section's other reports, as committed
        ((tmp_path / report).parent).mkdir(parents=True)
        shutil.copy(page.DOCS / report, tmp_path / report)
    record = {"preset": "torque", "gpu": "NVIDIA H200", "config": {"env": {"num_envs": 4096}}, "train_seconds": 600.0,
              "commands": ["python -m x"], "time_to_walk": None, "date": "2026-12-05"}
    path = tmp_path / "benchmarks/time_to_walk.json"
    path.parent.mkdir()
    path.write_text(json.dumps({"command": "python -m r --runs a", "records": [record]}))
    row = next(line for line in page.time_to_walk(tmp_path) if line.startswith("| `torque`"))
    assert row.endswith("| – | 2026-12-05 |")  # no raw ceiling measured: no ratio, not a crash
    del record["date"]
    path.write_text(json.dumps({"command": "python -m r --runs a", "records": [record]}))
    with pytest.raises(ValueError, match="docs/benchmarks/time_to_walk.json: the record of run 'torque' has no "
                                         "'date', which this page shows"):
        page.time_to_walk(tmp_path)
    (tmp_path / "benchmarks/env_throughput.json").write_text(json.dumps(
        {"meta": {"command": "c", "date": "d", "gpu": "g"}, "results": [{"num_envs": 8}]}))
    monkeypatch.setattr(page, "SECTIONS", (page.env_throughput,))
    with pytest.raises(ValueError, match="the env_throughput section: docs/benchmarks/env_throughput.json lack"
                                         "\\(s\\) 'raw_policy_steps_per_s' \\(KeyError\\)"):
        page.render(tmp_path)
    monkeypatch.setattr(page, "render", lambda: page.time_to_walk(tmp_path))  # the command: one line, exit 1
    with pytest.raises(SystemExit) as stop:
        page.main([])
    assert stop.value.code == 1 and capsys.readouterr().err.startswith("error: docs/benchmarks/time_to_walk.json")


def test_the_presets_cost_report_measured_the_committed_presets_step():
    """The page calls PRESET_COST the committed robust preset's cost: what that run set on its command line (the env
    count and ``--set`` items) must be the preset's own values, or the preset has moved on and the page's claim is
    stale (measure the preset again and point PRESET_COST at the new report)."""
    import json
    import shlex

    from lab.benchmarks.common import parse_overrides
    from tocabi_torchrl.config import preset_config
    from tocabi_torchrl.tree import get_path

    page = _page_module()
    meta = json.loads((page.DOCS / page.PRESET_COST).read_text())["meta"]
    argv = shlex.split(meta["command"])
    sets = argv[argv.index("--set") + 1:]
    sets = sets[:next((i for i, a in enumerate(sets) if a.startswith("--")), len(sets))]
    measured = {"env.num_envs": meta["num_envs"], **parse_overrides(sets)}
    assert meta["preset"] == "robust" and set(measured) >= {"env.num_envs", "env.control.actuators.delay_stride",
                                                             "ppo.steps_per_env"}
    preset = preset_config("robust")
    stale = {path: (value, get_path(preset, path)) for path, value in measured.items()
             if get_path(preset, path) != value}
    assert not stale, f"{page.PRESET_COST} measured (value, preset's now): {stale}"


def test_a_run_recorded_under_another_preset_is_named_with_the_recipe_it_trained():
    # The model_based run set its recipe over the robust preset on the command line: the page must not present it
    # as a run of the robust recipe.
    page = _page_module()
    first = page._test_time_to_walk(page.DOCS, page.MODEL_BASED_TIME_TO_WALK, page._DIVERSE_TEST)[0]
    assert "`robust` (with the overrides below, the `model_based` preset's recipe; seed 0)" in first
    assert "first passes at **7.0 min**" in first
    pd = page._test_time_to_walk(page.DOCS, page.PD_TIME_TO_WALK, page._DIVERSE_TEST)[0]
    assert "`robust` (with the overrides below, the `pd` preset's recipe; seed 0)" in pd
    assert "first passes at **4.0 min**" in pd
    torque = page._test_time_to_walk(page.DOCS, page.TORQUE_TIME_TO_WALK[0], page._DIVERSE_TEST)[0]
    assert "`torque` (seed 0)" in torque
