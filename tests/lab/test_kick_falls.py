"""lab/analysis/kick_falls.py's breakdown of falls by the time since a robot's previous kick."""

from __future__ import annotations

import doctest
import math

import pytest
import torch

from lab.analysis import kick_falls


def test_docstring_examples_run():
    result = doctest.testmod(kick_falls, optionflags=doctest.ELLIPSIS)
    assert result.attempted >= 3 and result.failed == 0


def test_each_kick_after_the_first_is_binned_once_and_only_the_last_before_a_fall_counts():
    inf = math.inf
    kick_s = torch.tensor([[2.0, 2.2, 6.5],    # falls at 3.0: the 0.2 s-gap kick is its last, the third never meets it
                           [5.9, 2.0, 4.4],    # unsorted: gaps 2.4 and 1.5; falls at 7.0 after the 1.5 s-gap kick
                           [2.0, 2.6, 4.0],    # stands: gaps 0.6 and 1.4
                           [3.0, 3.1, 3.2]])   # falls at 2.5, before any kick: nothing binned
    t_end = torch.tensor([3.0, 7.0, inf, 2.5])
    table = kick_falls.hazard_by_gap(kick_s, t_end)
    assert list(table) == ["<0.5 s", "0.5-1 s", "1-2 s", ">=2 s"]
    assert table["<0.5 s"] == {"met": 1, "falls": 1, "hazard": 1.0}
    assert table["0.5-1 s"] == {"met": 1, "falls": 0, "hazard": 0.0}
    assert table["1-2 s"] == {"met": 2, "falls": 1, "hazard": 0.5}
    assert table[">=2 s"] == {"met": 1, "falls": 0, "hazard": 0.0}
    assert sum(c["met"] for c in table.values()) == 5


def test_a_bin_no_kick_reaches_has_no_hazard():
    table = kick_falls.hazard_by_gap(torch.tensor([[2.0, 5.0]]), torch.tensor([math.inf]), edges=(1.0,))
    assert table == {"<1 s": {"met": 0, "falls": 0, "hazard": None}, ">=1 s": {"met": 1, "falls": 0, "hazard": 0.0}}


def test_value_around_kicks_groups_each_standing_kick_by_whether_its_robot_fell_after_it():
    values = torch.arange(100.0).repeat(3, 1) + torch.tensor([[0.0], [1000.0], [2000.0]])  # robot r, step t: 1000r + t
    kicks = torch.tensor([[60, 20],     # unsorted; falls at step 70: kick 20 stands, kick 60 is the one it fell after
                          [10, 98],     # stands; kick 98 + 2 is beyond the rollout: left out
                          [30, 80]])    # falls at step 25, before any kick: nothing counted
    t_end = torch.tensor([0.70, math.inf, 0.25])
    r = kick_falls.value_around_kicks(values, kicks, t_end, dt=0.01, offsets=(-1, 2))
    assert r["falls after"] == {"kicks": 1, "value": {-1: 59.0, 2: 62.0}}
    assert r["stands"] == {"kicks": 2, "value": {-1: (19.0 + 1009.0) / 2, 2: (22.0 + 1012.0) / 2}}


def test_value_around_kicks_with_no_kick_in_a_group_gives_none():
    r = kick_falls.value_around_kicks(torch.zeros(1, 10), torch.tensor([[5]]), torch.tensor([math.inf]), dt=0.01)
    assert r["falls after"] == {"kicks": 0, "value": {o: None for o in kick_falls.VALUE_OFFSETS}}
    assert r["stands"]["kicks"] == 0  # the default offsets reach 50 steps past the kick: beyond this rollout


def test_noting_terminations_notes_each_robots_first_condition_and_restores_the_env_function(monkeypatch):
    from tocabi_torchrl.envs import tocabi_walk

    steps = iter([{"neck_tilt": torch.tensor([False, True, False]), "any": torch.tensor([False, True, False])},
                  {"neck_tilt": torch.tensor([True, True, False]), "any": torch.tensor([True, True, False])}])

    def fake(**kwargs):
        return next(steps)

    monkeypatch.setattr(tocabi_walk, "termination_flags", fake)
    with kick_falls.noting_terminations({}) as first:
        for _ in range(2):
            tocabi_walk.termination_flags(pelvis_height=None)  # the env calls it by keyword, once per step
    assert first == {1: (1, "neck_tilt"), 0: (2, "neck_tilt")}
    assert tocabi_walk.termination_flags is fake


def test_an_existing_report_or_a_missing_checkpoint_is_refused_before_any_rollout(tmp_path, monkeypatch):
    # --out was written over whatever was there (a committed kick_falls.json), after minutes of rollouts.
    monkeypatch.setattr(kick_falls, "measure", lambda *a, **k: pytest.fail("ran a rollout"))
    checkpoint, out = tmp_path / "policy.pt", tmp_path / "kick_falls.json"
    checkpoint.write_bytes(b"")
    out.write_text("{}\n")
    with pytest.raises(SystemExit) as refused:
        kick_falls.main(["--checkpoint", str(checkpoint), "--out", str(out)])
    assert refused.value.code == 2 and out.read_text() == "{}\n"
    with pytest.raises(SystemExit) as missing:
        kick_falls.main(["--checkpoint", str(checkpoint), str(tmp_path / "no_such.pt")])
    assert missing.value.code == 2
