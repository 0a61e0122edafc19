"""The signal table (tocabi_torchrl.signals) is the one source of the env's specs, the reward terms' shape checks, the
transforms' mock and docs/concepts/env-and-signals.md; adding a signal is a table row plus the line that computes it."""

from __future__ import annotations

import re

import pytest
import torch
from mock_env import MockTocabiWalk
from tensordict import TensorDict
from torchrl.data import Bounded, Categorical, Unbounded
from torchrl.envs.utils import check_env_specs

from tocabi_torchrl import robot
from tocabi_torchrl.envs import TocabiWalk
from tocabi_torchrl.signals import EPISODE_FLAGS, REWARD, SIGNALS, Signal, SignalTable
from tocabi_torchrl.signals_doc import BEGIN, DOC_PATH, END, is_current, main, render_table, with_table
from tocabi_torchrl.transforms.reward_terms import REFERENCE_TERMS, SIGNAL_SHAPES

N = 2

# ---- A new signal, added in two places: its table row and the function that computes it. ----------------------
PELVIS_HEIGHT = Signal("pelvis_height", (1,), torch.float32, "m", "pelvis origin height above the ground")


class PelvisHeightWalk(TocabiWalk):
    signal_table = SIGNALS.with_rows(PELVIS_HEIGHT)

    def _observe(self) -> TensorDict:
        td = super()._observe()
        td["pelvis_height"] = self.sim.base_pos[:, 2:3].clone()
        return td


# ---------------------------------------------------------------------------------------------------------------


def _env(cls=TocabiWalk, **kwargs) -> TocabiWalk:
    return cls(num_envs=N, device="cpu", seed=0, backend="mujoco", **kwargs)


def test_docs_table_is_current():
    if not DOC_PATH.is_file():
        pytest.skip("docs/concepts/env-and-signals.md is not in this installation")
    assert is_current(DOC_PATH), "docs/concepts/env-and-signals.md is stale: run python -m tocabi_torchrl.signals_doc"


def test_env_specs_are_the_table():
    env = _env()
    spec = env.observation_spec
    assert list(spec.keys()) == [row.name for row in SIGNALS.enabled()]
    assert "leg_assist" not in spec.keys() and "leg_assist" in SIGNALS  # only with torque_assist
    for row in SIGNALS.enabled():
        assert spec[row.name] == row.spec(N, env.device), row.name
    assert isinstance(spec["phase"], Bounded) and isinstance(spec["stance"], Categorical)
    assert spec["stance"].space.n == 3 and spec["foot_contact"].dtype == torch.bool
    assert isinstance(spec["joint_pos"], Unbounded) and spec["joint_pos"].shape == (N, robot.NUM_JOINTS)
    assert list(env.done_spec.keys()) == list(EPISODE_FLAGS.names)
    assert env.reward_spec == REWARD.spec(N, env.device)
    td = env.reset()
    for row in SIGNALS.enabled():
        assert td[row.name].shape == (N, *row.shape) and td[row.name].dtype == row.dtype, row.name


def test_mock_specs_are_the_table():
    mock = MockTocabiWalk(N)
    assert mock.observation_spec == SIGNALS.composite(N, "cpu")
    check_env_specs(mock)


def test_reward_shape_checks_come_from_the_table():
    read = {k for term in REFERENCE_TERMS.values() for k in (*term.root_keys, *term.next_keys)}
    assert set(SIGNAL_SHAPES) == read
    assert all(SIGNAL_SHAPES[k] == SIGNALS[k].shape for k in read)
    assert SIGNAL_SHAPES["foot_force"] == (2, 3) and SIGNAL_SHAPES["applied_action"] == (robot.NUM_LEG_JOINTS + 1,)


def test_a_new_signal_reaches_specs_observations_mock_and_docs(tmp_path):
    table = PelvisHeightWalk.signal_table
    # Specs and the observed tensordict of the real env, reset and step.
    env = _env(PelvisHeightWalk)
    assert env.observation_spec["pelvis_height"] == PELVIS_HEIGHT.spec(N, env.device)
    check_env_specs(env, seed=0)
    td = env.reset()
    torch.testing.assert_close(td["pelvis_height"], env.sim.base_pos[:, 2:3])
    nxt = env.step(td.set("action", torch.zeros(N, 13)))["next"]
    torch.testing.assert_close(nxt["pelvis_height"], env.sim.base_pos[:, 2:3])
    assert 0.5 < float(nxt["pelvis_height"].min()) < 1.0
    # The mock emits it too, from the same row.
    mock = MockTocabiWalk(N, mode="counter", signals=table)
    assert mock.observation_spec["pelvis_height"] == PELVIS_HEIGHT.spec(N, "cpu")
    step = mock.rollout(3)
    assert step["next", "pelvis_height"].shape == (N, 3, 1)
    torch.testing.assert_close(step["next", "pelvis_height"][0, :, 0], torch.tensor([1.0, 2.0, 3.0]))
    check_env_specs(MockTocabiWalk(N, signals=table))
    # The docs check sees the committed page as stale until it is regenerated.
    assert "| `pelvis_height` | (N, 1) | float32 | m | pelvis origin height above the ground |" in render_table(table)
    page = tmp_path / "signals.md"
    page.write_text(DOC_PATH.read_text() if DOC_PATH.is_file() else f"# Signals\n\n{render_table()}\n")
    assert is_current(page) and not is_current(page, table)
    page.write_text(with_table(page.read_text(), table))
    assert is_current(page, table) and not is_current(page)


def test_docs_command_line(tmp_path, capsys):
    page = tmp_path / "signals.md"
    page.write_text(f"# Signals\n\nprose\n\n{render_table(SignalTable(SIGNALS.rows[:3]))}\n\nmore prose\n")
    assert main(["--check", "--path", str(page)]) == 1
    assert "stale" in capsys.readouterr().err
    assert main(["--path", str(page)]) == 0
    assert main(["--check", "--path", str(page)]) == 0
    text = page.read_text()
    assert text.startswith("# Signals\n\nprose\n\n") and text.endswith("\n\nmore prose\n")
    assert all(f"| `{name}` |" in text for name in SIGNALS.names)


@pytest.mark.parametrize(
    "text,match",
    [
        ("# Signals without markers\n", "lacks the marker line .*BEGIN"),
        (f"# Signals\n\n{BEGIN}\n| old |\n", "lacks the marker line .*END"),
        (f"# Signals\n\n{END}\n{render_table()[: -len(END)]}", "lacks the marker line .*END"),
    ],
)
def test_docs_command_line_refuses_a_page_without_markers(tmp_path, capsys, text, match):
    """A page that lacks a marker (or has END only above BEGIN) is a one-line usage error, not a traceback."""
    page = tmp_path / "signals.md"
    page.write_text(text)
    for argv in (["--check", "--path", str(page)], ["--path", str(page)]):
        with pytest.raises(SystemExit) as stop:
            main(argv)
        assert stop.value.code == 2
        assert re.search(match, capsys.readouterr().err)
    assert page.read_text() == text


def test_table_is_found_after_a_stray_end_marker(tmp_path):
    """END is looked for after BEGIN: an END line above the table does not hide the table."""
    page = tmp_path / "signals.md"
    page.write_text(f"# Signals\n\n{END}\nprose\n\n{BEGIN}\n| old |\n{END}\n\nmore prose\n")
    assert not is_current(page)
    assert main(["--path", str(page)]) == 0
    assert page.read_text() == f"# Signals\n\n{END}\nprose\n\n{render_table()}\n\nmore prose\n"
    assert is_current(page)


def test_docs_command_line_refuses_a_directory(tmp_path, capsys):
    with pytest.raises(SystemExit) as stop:
        main(["--check", "--path", str(tmp_path)])
    assert stop.value.code == 2
    err = capsys.readouterr().err
    assert "is not a file" in err and "does not exist" not in err


def test_env_refuses_a_signal_the_table_lacks_or_a_row_it_does_not_compute():
    class Unlisted(TocabiWalk):  # computes a signal but has no row for it
        def _observe(self):
            return super()._observe().set("pelvis_height", self.sim.base_pos[:, 2:3].clone())

    class Uncomputed(TocabiWalk):  # a row nobody computes
        signal_table = SIGNALS.with_rows(PELVIS_HEIGHT)

    class WrongShape(PelvisHeightWalk):
        signal_table = SIGNALS.with_rows(Signal("pelvis_height", (3,), torch.float32, "m", "pelvis origin"))

    with pytest.raises(KeyError, match=r"returns \['pelvis_height'\] that the signal table lacks"):
        _env(Unlisted)
    with pytest.raises(KeyError, match=r"lacks \['pelvis_height'\] that it lists"):
        _env(Uncomputed)
    with pytest.raises(ValueError, match=r"'pelvis_height' as \(2, 1\) torch.float32.*\(3,\)"):
        _env(WrongShape)


def test_conditional_signal_follows_the_config():
    row = SIGNALS["leg_assist"]
    assert row.requires == "torque_assist"
    assert not row.enabled(None) and "leg_assist" not in [r.name for r in SIGNALS.enabled()]
    assisted_flags = {"torque_assist": True, "model_based": False, "obstacles": False, "pushes": False,
                      "cycle_velocity": False}
    assert not row.enabled({"torque_assist": False}) and SIGNALS.enabled(assisted_flags)[-1] is row
    assert _env().signal_flags() == {"torque_assist": False, "model_based": False, "obstacles": False, "pushes": False,
                                     "cycle_velocity": False}
    assisted = _env(torque_assist=True, control_mode="torque")
    assert assisted.signal_flags() == assisted_flags
    assert list(assisted.observation_spec.keys())[-1] == "leg_assist"
    assert assisted.reset()["leg_assist"].shape == (N, robot.NUM_LEG_JOINTS)
    with pytest.raises(KeyError, match="requires the option 'torque_assist'"):
        SIGNALS.enabled({"other": True})


@pytest.mark.parametrize(
    "kwargs, error, match",
    [
        ({"name": "foot slip"}, ValueError, "identifiers"),
        ({"shape": (0,)}, ValueError, "positive ints"),
        ({"dtype": torch.float64}, ValueError, "dtype must be one of"),
        ({"meaning": "a | b"}, ValueError, "without '|'"),
        ({"categories": 3}, ValueError, "categories"),
        ({"bounds": (1.0, 0.0)}, ValueError, "low < high"),
    ],
)
def test_bad_rows(kwargs, error, match):
    row = {"name": "x", "shape": (1,), "dtype": torch.float32, "unit": "m", "meaning": "x"} | kwargs
    with pytest.raises(error, match=match):
        Signal(**row)


def test_table_lookup_and_duplicates():
    assert SIGNALS["foot_force"].shape == (2, 3) and "foot_force" in SIGNALS and "nope" not in SIGNALS
    with pytest.raises(KeyError, match="no signal 'nope'"):
        SIGNALS["nope"]
    with pytest.raises(ValueError, match="'joint_pos' appears twice"):
        SIGNALS.with_rows(SIGNALS["joint_pos"])
    assert SIGNALS["foot_contact"].categories == 2  # bool rows are two-valued flags
