"""lab/benchmarks/randomization_cost.py: its two variants are the preset with and without every randomisation piece
(a piece missing from ``OFF`` would leave "off" partly randomised), and it runs end to end at toy size on the CPU."""

from __future__ import annotations

import json
import os

import pytest

from lab.benchmarks import common, randomization_cost


def _config(items):
    overrides = common.parse_overrides(items)
    return common.run_config(8, 2, overrides, "/tmp/unused", "x", "cpu")


def test_off_switches_every_piece_off_and_on_is_the_preset_with_full_kicks():
    from tocabi_torchrl.config import preset_config
    from tocabi_torchrl.control.config import ActuatorConfig

    sets = randomization_cost.variants("robust", [])
    on, off = _config(sets["on"]), _config(sets["off"])
    preset = preset_config("robust")
    assert on.env.dynamics == preset.env.dynamics and on.env.pushes == preset.env.pushes
    assert on.transforms.sensor_noise == preset.transforms.sensor_noise and on.env.task.diverse_starts
    assert on.ppo.push_ramp == (0, 0) and preset.ppo.push_ramp != (0, 0)
    assert not off.env.dynamics.enabled and off.env.control.actuators == ActuatorConfig()
    assert not off.transforms.sensor_noise.enabled and off.env.pushes.count == 0 and not off.env.task.diverse_starts
    # Everything else is the same (the PPO with its symmetry and privileged critic, the rewards, the schedules, the
    # start pool...): only the paths OFF names differ, leaf by leaf.
    from tocabi_torchrl.tree import get_path, leaf_paths

    named = {item.partition("=")[0] for item in randomization_cost.OFF}
    differ = {path for path in leaf_paths(on) if get_path(on, path) != get_path(off, path)}
    assert differ and differ <= named, differ - named


@pytest.mark.parametrize("shape", ["env.control.actuators.delay_stride=4", "env.control.actuators.delay_average=true"])
def test_off_is_valid_when_the_measured_preset_shapes_its_delay(shape):
    # A delay grid or averaged delay without a delay is refused by the config: off must reset them with the delay, or
    # a measurement of a delay-shaping variant dies at its first off child.
    from tocabi_torchrl.config import preset_config
    from tocabi_torchrl.control.config import ActuatorConfig

    sets = randomization_cost.variants("robust", [shape])
    on, off = _config(sets["on"]), _config(sets["off"])
    assert on.env.control.actuators != preset_config("robust").env.control.actuators  # the shaping reached on
    assert off.env.control.actuators == ActuatorConfig()


def test_it_measures_both_variants_alternately_and_reports_their_ratio(tmp_path):
    randomization_cost.main(["--device", "cpu", "--num_envs", "8", "--rounds", "1", "--iterations", "1", "--warmup",
                             "1", "--raw_steps", "0", "--set", "ppo.steps_per_env=8", "ppo.actor_hidden=8 8",
                             "ppo.critic_hidden=8 8", "ppo.minibatch_size=32", "--out", str(tmp_path),
                             "--run_dir", str(tmp_path / "runs")])
    data = json.loads((tmp_path / "randomization_cost.json").read_text())
    assert [r["variant"] for r in data["results"]] == ["on", "off"]
    on, off = data["results"]
    assert "env.pushes.count" not in on["overrides"] and on["overrides"]["preset"] == "robust"
    assert off["overrides"]["env.pushes.count"] == 0 and off["overrides"]["ppo.push_ramp"] == [0, 0]
    ratio = on["train_env_steps_per_s"] / off["train_env_steps_per_s"]
    assert abs(data["summary"]["on_over_off"] - ratio) < 1e-9
    assert f"on / off = **{ratio:.3f}**" in (tmp_path / "randomization_cost.md").read_text()

    # The benchmarks page shows the measurement above the earlier per-piece table once the report is committed.
    from lab.benchmarks import page

    docs = tmp_path / "docs"
    (docs / "benchmarks" / "randomization").mkdir(parents=True)
    for name in ("train_throughput.json", "step_ops.json", "substep_iterations.json"):
        (docs / "benchmarks" / "randomization" / name).write_text((page.DOCS / "benchmarks" / "randomization" /
                                                                   name).read_text())
    section = "\n".join(page.randomization(docs))
    assert "randomization_cost.json" not in section  # not measured: the section is the earlier one alone
    (docs / page.RANDOMIZATION_COST).write_text((tmp_path / "randomization_cost.json").read_text())
    section = "\n".join(page.randomization(docs))
    assert f"**{ratio:.3f}x**" in section and ("meets" if ratio >= 0.95 else "misses") in section
    assert section.index("randomization_cost.json") < section.index("train_throughput.json")


def test_each_piece_owns_its_off_items_and_comes_back_alone():
    from tocabi_torchrl.tree import get_path, leaf_paths

    owners = {item: [n for n, prefixes in randomization_cost.PIECES.items() if item.startswith(prefixes)]
              for item in randomization_cost.OFF}
    assert all(len(v) == 1 for v in owners.values()), owners  # every OFF item belongs to one piece
    sets = randomization_cost.variants("robust", [], tuple(randomization_cost.PIECES))
    off = _config(sets["off"])
    for name, prefixes in randomization_cost.PIECES.items():
        alone = _config(sets[f"off+{name}"])
        differ = {path for path in leaf_paths(off) if get_path(off, path) != get_path(alone, path)}
        assert differ and all(path.startswith(prefixes) for path in differ), (name, differ)
    import pytest

    with pytest.raises(ValueError, match="unknown piece"):
        randomization_cost.variants("robust", [], ("lighting",))


def test_physics_measures_each_variant_in_a_solver_load_child_and_reports_the_ratio(tmp_path, monkeypatch):
    calls = []

    def fake_child(module, args, env=None, nproc=None):
        calls.append((module, list(args)))
        items = args[args.index("--set") + 1:]
        if module == "train_throughput":
            return {"train_env_steps_per_s": 100.0 if "env.pushes.count=0" in items else 90.0}
        # The "off" variant's physics is quicker: its robots are neither kicked nor randomised.
        ms = 2.0 if "env.pushes.count=0" in items else 2.5
        return {"training": {"ms_per_policy_step": ms, "niter_max_over_worlds": 7.0, "niter_mean": 2.0,
                             "niter_max_seen": 9.0, "constraint_rows_per_world": 40.0, "contacts_per_world": 2.0}}

    monkeypatch.setattr(common, "run_child", fake_child)
    randomization_cost.main(["--device", "cpu", "--num_envs", "8", "--rounds", "1", "--physics", "--out",
                             str(tmp_path), "--run_dir", str(tmp_path / "runs")])
    physics_calls = [args for module, args in calls if module == "solver_load"]
    assert len(physics_calls) == 2 and all(a[a.index("--num_envs") + 1] == "8" for a in physics_calls)
    assert {"env.pushes.count=0" in a for a in physics_calls} == {True, False}
    data = json.loads((tmp_path / "randomization_cost.json").read_text())
    assert set(data["physics"]) == {"on", "off"}
    assert data["summary"]["physics_off_over_on"] == 2.0 / 2.5
    assert data["summary"]["on_over_off"] == 0.9
    text = (tmp_path / "randomization_cost.md").read_text()
    assert "Physics time off / on = **0.800**" in text and "| on | 2.500 | 7.00 |" in text


def test_each_round_trains_its_own_seed_and_the_ratio_is_the_median_of_the_rounds(tmp_path, monkeypatch, capsys):
    # One seed's first iterations are one sample of how hard the flailing robots' physics is: the rounds differ in
    # seed, both variants of a round share it, and the ratio is the median of the rounds' own ratios.
    rates = {("on", 0): 90.0, ("off", 0): 100.0, ("on", 1): 99.0, ("off", 1): 110.0, ("on", 2): 50.0,
             ("off", 2): 100.0}
    seen = []

    def fake_child(module, args, env=None, nproc=None):
        items = args[args.index("--set") + 1:]
        seed = int(next(i for i in items if i.startswith("seed=")).partition("=")[2])
        variant = "off" if "env.pushes.count=0" in items else "on"
        seen.append((variant, seed))
        return {"train_env_steps_per_s": rates[(variant, seed)]}

    monkeypatch.setattr(common, "run_child", fake_child)
    randomization_cost.main(["--device", "cpu", "--num_envs", "8", "--rounds", "3", "--out", str(tmp_path),
                             "--run_dir", str(tmp_path / "runs")])
    assert seen == [("on", 0), ("off", 0), ("off", 1), ("on", 1), ("on", 2), ("off", 2)]  # alternating order
    data = json.loads((tmp_path / "randomization_cost.json").read_text())
    assert data["meta"]["seeds"] == [0, 1, 2] and [r["seed"] for r in data["results"]] == [0, 0, 1, 1, 2, 2]
    assert data["summary"]["round_on_over_off"] == [0.9, 0.9, 0.5]
    assert data["summary"]["on_over_off"] == 0.9  # the median of the rounds, not median(on) / median(off) = 0.9/1
    assert "0.900, 0.900, 0.500" in (tmp_path / "randomization_cost.md").read_text()

    seen.clear()
    randomization_cost.main(["--device", "cpu", "--num_envs", "8", "--rounds", "1", "--seeds", "2", "--name", "b",
                             "--out", str(tmp_path), "--run_dir", str(tmp_path / "runs")])
    assert seen == [("on", 2), ("off", 2)]
    import pytest

    capsys.readouterr()
    seen.clear()
    for bad, said in ((["--rounds", "2", "--seeds", "1"], "--seeds takes one seed per round: 2 round(s), got 1"),
                      (["--set", "seed=3"], "set the rounds' seeds with --seeds, not --set seed=...")):
        with pytest.raises(SystemExit):
            randomization_cost.main(["--device", "cpu", *bad, "--out", str(tmp_path / "no")])
        assert said in capsys.readouterr().err
    assert seen == [] and not (tmp_path / "no").exists()  # refused before any run


def test_a_report_there_already_is_refused_before_any_measurement_unless_overwrite(tmp_path, monkeypatch, capsys):
    # A series of --set variants into the default --out once kept only the last: each replaced the one before it
    # (and the first the committed report) without a word.
    import pytest

    calls = []

    def fake_child(module, args, env=None, nproc=None):
        calls.append(module)
        return {"train_env_steps_per_s": 100.0}

    monkeypatch.setattr(common, "run_child", fake_child)
    (tmp_path / "randomization_cost.json").write_text('{"earlier": true}')
    argv = ["--device", "cpu", "--num_envs", "8", "--rounds", "1", "--out", str(tmp_path), "--run_dir",
            str(tmp_path / "runs")]
    with pytest.raises(SystemExit) as stop:
        randomization_cost.main(argv)
    assert stop.value.code == 2 and "pass --overwrite to replace it" in capsys.readouterr().err
    assert not calls and json.loads((tmp_path / "randomization_cost.json").read_text()) == {"earlier": True}
    randomization_cost.main([*argv, "--overwrite"])
    assert calls and "summary" in json.loads((tmp_path / "randomization_cost.json").read_text())


def test_a_report_that_appears_during_the_measurement_is_replaced_only_with_overwrite(tmp_path, monkeypatch,
                                                                                      capsys):
    # The report was checked for before the minutes of measurement and written with replace after them: one that
    # appeared in between (another variant's, measured beside) was replaced unsaid; then refused with
    # FileExistsError, losing the measurement. The pair goes beside it now, and one line says where.
    report = tmp_path / "randomization_cost.json"

    def measure(module, args, raw_steps, run_name, items):
        report.exists() or report.write_text("{}\n")
        return {"train_env_steps_per_s": 100.0}

    monkeypatch.setattr(randomization_cost, "_measure", measure)
    argv = ["--device", "cpu", "--rounds", "1", "--out", str(tmp_path), "--run_dir", str(tmp_path / "runs")]
    randomization_cost.main(argv)
    assert report.read_text() == "{}\n" and not (tmp_path / "randomization_cost.md").exists()
    beside = tmp_path / f"randomization_cost.{os.getpid()}.json"
    assert json.loads(beside.read_text())["summary"]["on_over_off"] == 1.0
    page = tmp_path / f"randomization_cost.{os.getpid()}.md"
    assert page.is_file()
    warning = capsys.readouterr().err
    assert f"{report} appeared" in warning and str(beside) in warning and str(page) in warning
    report.unlink()
    randomization_cost.main([*argv, "--overwrite"])
    assert json.loads(report.read_text())["summary"]["on_over_off"] == 1.0


def test_a_user_setting_that_off_replaces_is_not_called_given_twice(tmp_path, monkeypatch, capsys):
    # --set env.control.actuators.delay_stride=2 printed "delay_stride is given 2 times; the last applies:
    # delay_stride=1" (off's identity item), which read as if the user's setting were lost in both variants.
    sent = {}

    def fake_child(module, args, env=None, nproc=None):
        items = args[args.index("--set") + 1:]
        sent["off" if "env.pushes.count=0" in items else "on"] = items
        return {"train_env_steps_per_s": 100.0}

    monkeypatch.setattr(common, "run_child", fake_child)
    argv = ["--device", "cpu", "--num_envs", "8", "--rounds", "1", "--out", str(tmp_path), "--run_dir",
            str(tmp_path / "runs"), "--set", "env.control.actuators.delay_stride=2"]
    randomization_cost.main(argv)
    assert "given 2 times" not in capsys.readouterr().err
    assert "env.control.actuators.delay_stride=2" in sent["on"]
    assert sent["off"].index("env.control.actuators.delay_stride=1") > sent["off"].index(
        "env.control.actuators.delay_stride=2")  # off's identity comes last and applies
    randomization_cost.main([*argv, "ppo.lr=1e-4", "ppo.lr=2e-4", "--name", "twice"])
    assert capsys.readouterr().err.count("ppo.lr is given 2 times") == 1  # the user's own repeat, said once


def test_a_user_s_push_ramp_applies_in_every_variant(tmp_path, monkeypatch, capsys):
    # The variants' own ppo.push_ramp=0 0 came after the user's --set items and replaced a --set ppo.push_ramp in
    # every variant; with the repeat warning kept to the user's own items, without a word.
    sent = {}

    def fake_child(module, args, env=None, nproc=None):
        items = args[args.index("--set") + 1:]
        sent["off" if "env.pushes.count=0" in items else "on"] = common.parse_overrides(items, warn_repeats=False)
        return {"train_env_steps_per_s": 100.0}

    monkeypatch.setattr(common, "run_child", fake_child)
    randomization_cost.main(["--device", "cpu", "--num_envs", "8", "--rounds", "1", "--out", str(tmp_path),
                             "--run_dir", str(tmp_path / "runs"), "--set", "ppo.push_ramp=100 200"])
    assert sent["on"]["ppo.push_ramp"] == sent["off"]["ppo.push_ramp"] == (100, 200)
    assert "given 2 times" not in capsys.readouterr().err
    assert common.parse_overrides(randomization_cost.variants("robust", [])["on"])["ppo.push_ramp"] == (0, 0)
