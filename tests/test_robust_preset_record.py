"""The committed ``robust`` preset is the configuration of the from-scratch run that shows it walks.

A preset "walks" only by the gait test of a from-scratch run of the committed preset (docs/training.md). The run's
record keeps the whole config it trained with (``config.json``); if a preset value changes after the run, the record
no longer speaks for the preset, and this test says so.
"""
import argparse
import json
from pathlib import Path

from lab.benchmarks import time_to_walk
from tocabi_torchrl.config import config_from_dict, preset_config, to_dict

RECORD = Path(__file__).resolve().parents[1] / "docs" / "training" / "robust" / "h100_run23"

#: What ``lab.benchmarks.time_to_walk train`` sets for every run it trains, whatever the preset: where the run lives,
#: how long one call trains, how it logs and checkpoints, and which file it resumes. None of them changes what is
#: learned.
RUN_MECHANICS = tuple(time_to_walk.run_mechanics(argparse.Namespace(name="x", device="cpu", log_every=5, every=0.5,
                                                                    minutes=1.0), Path("absent.pt"), 1.0))


def _differences(a, b, path=""):
    if isinstance(a, dict) and isinstance(b, dict):
        return [d for key in sorted(set(a) | set(b)) for d in _differences(a.get(key, "<absent>"),
                                                                          b.get(key, "<absent>"), f"{path}.{key}")]
    return [] if a == b else [f"{path.lstrip('.')}: preset {a!r}, record {b!r}"]


def _plain(cfg) -> dict:
    return json.loads(json.dumps({k: v for k, v in to_dict(cfg).items() if k not in RUN_MECHANICS}))


def _record_name() -> str:
    return json.loads((RECORD / "config.json").read_text())["name"]


def test_robust_preset_is_the_passing_runs_config():
    record = config_from_dict(json.loads((RECORD / "config.json").read_text()))
    assert record.preset == "robust"
    differences = _differences(_plain(preset_config("robust")), _plain(record))
    assert not differences, "the robust preset is not the config of its passing run " + str(RECORD) + ":\n" + \
        "\n".join(differences)


def test_the_record_is_the_run_that_passed():
    """The record the test above reads is the run whose checkpoints passed the robust gait test."""
    report = json.loads((RECORD / "time_to_walk_robust.json").read_text())
    assert report["test"] == "robust"
    (run,) = report["records"]
    assert run["name"] == _record_name() and run["preset"] == "robust"
    assert run["time_to_walk"] is not None and run["time_to_walk"]["train_minutes"] <= 30.0


def test_the_comparison_sees_a_changed_value():
    changed = preset_config("robust", **{"ppo.desired_kl": 0.01})
    expected = ["ppo.desired_kl: preset 0.01, record 0.02"]
    assert _differences(_plain(changed), _plain(preset_config("robust"))) == expected
