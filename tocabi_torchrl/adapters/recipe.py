"""What the library recipes (``recipes/train_<library>.py``) share: their common options, the output folder, the
training clock and the resume state (``--resume``).

A run can be trained over several calls: each call ends by writing the library's own training state as a new file
``<out>/resume/state_call<k>.pt`` and then, atomically, ``<out>/resume.json``, which names that file and carries the
cumulative counters (env steps, training seconds, PPO iterations, snapshots). ``--resume`` continues from there;
``--max_minutes`` is then the cap on the *total* training time over all calls. The rollout in progress when a call's
time is up is discarded (its env steps and seconds still count: they were spent), and every call starts its envs from
a reset.

A call stopped by Ctrl-C or SIGTERM (:func:`stop_on_signals`) ends the same way: at the next env step it saves its
resume state and ``policy.pt``, skips the gait test and says how to resume.
"""

from __future__ import annotations

import argparse
import contextlib
import io
import json
import math
import sys
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path

from ..atomic import atomic_write_text
from ..cli import base_parser, hidden_sizes  # light: a recipe parses its options before the heavy imports
from ..config import check_snapshot_minutes, wall_tag
from ..rl.interrupt import Interrupted, exit_status
from ..rl.interrupt import stop_on_signals as _stop_on_signals

__all__ = [
    "Interrupted",
    "adapter",
    "TimeUp",
    "TrainingClock",
    "base_parser",
    "call_seed",
    "check_args",
    "check_out_dir",
    "eval_text",
    "exit_status",
    "finish_call",
    "fresh_dir",
    "hidden_sizes",
    "keep_previous",
    "open_out_dir",
    "read_resume",
    "report_interruption",
    "run_call",
    "stop_on_signals",
    "write_json",
    "write_resume",
]


def adapter(name: str):
    """The adapter class ``name`` (e.g. ``"TocabiSB3VecEnv"``), which imports its library and checks its version; a
    missing library or one of an unsupported version ends the recipe with one ``error:`` line and its install
    command (not a traceback)."""
    from .. import adapters
    from ._versions import LibraryVersionError

    try:
        return getattr(adapters, name)  # the package's lazy import, or what the module already holds
    except LibraryVersionError as err:
        raise SystemExit(f"error: {err}") from None


def _check_number(args: argparse.Namespace, name: str, low: float, strict: bool = False) -> None:
    value = getattr(args, name)
    if not (math.isfinite(value) and (value > low if strict else value >= low)):
        raise ValueError(f"--{name} must be a finite number {'>' if strict else '>='} {low:g}, got {value!r}")


def check_args(parser: argparse.ArgumentParser, args: argparse.Namespace, at_least: Mapping[str, int] | None = None,
               positive: Sequence[str] = ()) -> None:
    """Check the options of :func:`base_parser` and a recipe's own, right after parsing and before anything is built
    or written: a bad value ends the call through ``parser.error`` (the usage and one line naming the option, the
    value and what it may be; exit status 2), so it leaves no output folder behind. ``at_least``: the recipe's own
    int options and their lowest value (``{"n_steps": 1}``); ``positive``: its float options that must be finite and
    > 0 (learning rates). ``--hidden`` is checked where it is parsed (:func:`hidden_sizes`).

    The checks are the project's own: ``config``'s int check and snapshot period (the trainer's), the device as the
    env resolves it (``auto``, ``cpu``, ``cuda``, ``cuda:N``; CUDA only where torch sees a GPU), the preset's name
    and the gait test's length of at least one policy step. Unless ``--eval_envs 0``, the gait test after training
    needs matplotlib (for ``knees.png``): without it the call ends here with one ``error:`` line and the install
    command, not after training with a traceback."""
    from ..config import _check_int, check_snapshot_minutes, preset_tree
    from ..evaluation.gait_test import policy_dt, policy_steps
    from ..rl.trainer import resolve_device

    try:
        for name, low in {"num_envs": 1, "iterations": 1, "eval_envs": 0, **(at_least or {})}.items():
            _check_int(args, name, low, "--")
        _check_number(args, "max_minutes", 0.0)
        _check_number(args, "checkpoint_minutes", 0.0)
        check_snapshot_minutes(args.checkpoint_minutes, "--checkpoint_minutes")
        _check_number(args, "eval_seconds", 0.0, strict=True)
        for name in positive:
            _check_number(args, name, 0.0, strict=True)
        if not 0 <= args.seed < 2 ** 32:  # the libraries seed NumPy with it, which takes no other value
            raise ValueError(f"--seed must be an int in [0, 2**32 - 1], got {args.seed!r}")
    except ValueError as err:
        parser.error(str(err))
    try:
        policy_steps(args.eval_seconds, policy_dt())
    except ValueError as err:
        parser.error(f"--eval_seconds: {err}")
    try:
        preset_tree(args.preset)
    except ValueError as err:
        parser.error(f"--preset: {err}")
    try:
        resolve_device(args.device)
    except (ValueError, RuntimeError) as err:  # RuntimeError: CUDA asked for where torch sees no GPU
        parser.error(f"--device: {err}" + (" (or 'auto')" if isinstance(err, ValueError) else ""))
    if args.eval_envs > 0:
        from .evaluate import check_plotting

        try:
            check_plotting()
        except ImportError as err:  # a missing dependency, as adapter() reports one: no usage text
            raise SystemExit(f"error: {err}; or pass --eval_envs 0 to skip the gait test") from None


def check_out_dir(path: str, resume: bool = False) -> Path:
    """What :func:`open_out_dir` checks, creating nothing: a recipe calls this first and creates the folder only
    once its env is built, so a call that fails before (a bad option, an env that cannot be built) leaves no folder
    that a rerun with the same ``--out`` would be refused for."""
    out = Path(path)
    if resume:
        if not (out / "resume.json").is_file():
            raise SystemExit(f"error: --resume needs {out / 'resume.json'} (written at the end of every call)")
    elif out.exists():
        raise SystemExit(f"error: {out} exists; pass another --out (an earlier run is never overwritten)")
    return out


def open_out_dir(path: str, resume: bool = False) -> Path:
    """Create the run's output folder; ``SystemExit`` with a message if it exists (an earlier run is kept). With
    ``resume`` the folder must exist and hold ``resume.json`` (a run this recipe wrote)."""
    out = check_out_dir(path, resume)
    if not resume:
        out.mkdir(parents=True)
    return out


def write_json(path: Path, data: dict) -> None:
    atomic_write_text(path, json.dumps(data, indent=2))


def call_seed(seed: int, calls: int) -> int:
    """The seed of a run's call after ``calls`` earlier ones: ``seed + calls`` (a resumed call draws other noise),
    wrapped into [0, 2**32 - 1], the only range NumPy's seeding (the libraries') takes, so that every ``--seed``
    :func:`check_args` accepts also resumes."""
    return (int(seed) + int(calls)) % 2 ** 32


def _is_int(value, low: int) -> bool:
    return isinstance(value, int) and not isinstance(value, bool) and value >= low


#: What every recipe writes into ``resume.json`` (besides ``state``) and reads back on ``--resume``.
RESUME_FIELDS = {
    "settings": ("an object", lambda v: isinstance(v, dict)),
    "calls": ("an int >= 1", lambda v: _is_int(v, 1)),
    "env_steps": ("an int >= 0", lambda v: _is_int(v, 0)),
    "iterations": ("an int >= 0", lambda v: _is_int(v, 0)),
    "train_seconds": ("a finite number >= 0", lambda v: isinstance(v, (int, float)) and not isinstance(v, bool)
                      and math.isfinite(v) and v >= 0),
    "snapshots": ("a list of paths", lambda v: isinstance(v, list) and all(isinstance(x, str) for x in v)),
    "state": ("a path", lambda v: isinstance(v, str)),
}


def read_resume(out: Path, torch_state: bool = False, keep_bytes: bool = False) -> dict:
    """The counters of ``<out>/resume.json``: ``env_steps``, ``train_seconds``, ``iterations``, ``snapshots``,
    ``calls``, ``state`` (the library state file, relative to ``out``) and ``settings`` (the options to check).

    A file that is not JSON, or lacks one of these fields or holds a value of the wrong kind (a hand edit, a copy cut
    short), ends the call with ``SystemExit`` and an ``error:`` line naming the field, before anything is built.
    The libraries' own loaders unpickle that state file, so it must be one this recipe wrote: ``state`` has to name
    an existing file inside ``<out>/resume/``, or ``SystemExit`` says so (a resume.json pointing elsewhere is
    refused before anything is loaded). ``torch_state``: the file is a torch checkpoint (rsl_rl's, skrl's), and it
    must load with ``torch.load(weights_only=True)`` (tensors and plain containers only), so the library's own
    unpickling loader then meets nothing that could run code. The file is read once: with ``torch_state`` (or
    ``keep_bytes``, for a recipe that checks the state itself) the returned dict also holds ``state_bytes``, the
    bytes checked, which the recipe hands to the library's loader (``io.BytesIO``) instead of the path, so that a
    file replaced after the check (the env takes a while to build) is never unpickled or loaded."""
    out = Path(out)
    path = out / "resume.json"
    fix = "restore the file this recipe wrote, or start a new --out"
    try:
        prior = json.loads(path.read_text())
    except (UnicodeDecodeError, json.JSONDecodeError) as err:
        raise SystemExit(f"error: {path} is not readable JSON ({err}); {fix}") from None
    if not isinstance(prior, dict):
        raise SystemExit(f"error: {path} holds {type(prior).__name__}, not the object of counters a call writes; {fix}")
    for name, (kind, ok) in RESUME_FIELDS.items():
        if name not in prior:
            raise SystemExit(f"error: {path} lacks {name!r}, which every call writes; {fix}")
        if not ok(prior[name]):
            raise SystemExit(f"error: {path} has {name}={prior[name]!r}, which must be {kind}; {fix}")
    from .policy_file import iso_day

    # Absent: a file from before the field, read as older than every rename; anything else must be the day it names.
    if "written" in prior and not iso_day(prior["written"]):
        raise SystemExit(f"error: {path} has written={prior['written']!r}, which must be the UTC day a call wrote it "
                         f"(YYYY-MM-DD); {fix}")
    _preset_now(prior)
    state = (out / prior["state"]).resolve()
    if state.parent != (out / "resume").resolve():
        raise SystemExit(f"error: {path} names {prior['state']!r} as its state file; a resume loads only a state this "
                         f"recipe wrote into {out / 'resume'}/ (start a new --out instead)")
    if not state.is_file():  # deleted, or left behind when the run folder was copied
        raise SystemExit(f"error: {path} names {prior['state']!r} as its state file, but {state} is missing; restore "
                         f"it (copy the whole run folder) or start a new --out")
    from ..integrity import zip_damage

    data = state.read_bytes()
    damage = zip_damage(io.BytesIO(data))
    if damage is not None:  # bits changed on disk or in a copy: torch.load would read other weights silently
        raise SystemExit(f"error: {state} is damaged: {damage}; restore the file from a copy or start a new --out")
    if torch_state:
        import torch

        try:
            torch.load(io.BytesIO(data), map_location="cpu", weights_only=True)
        except Exception as err:  # any refusal means the file is not what this recipe wrote
            raise SystemExit(f"error: {state} does not load as tensors only ({type(err).__name__}: {err}); a resume "
                             "never unpickles other objects (start a new --out instead)") from err
        return {**prior, "state_bytes": data}
    return {**prior, "state_bytes": data} if keep_bytes else prior


def _preset_now(prior: dict) -> None:
    """Read the saved settings' preset under its name now (``config.preset_now``), in place: a resume.json written
    before a preset was renamed (one without ``written``, the day it was written) names the recipe it ran by its
    name then, which may now name another recipe."""
    from ..config import preset_now

    preset = prior["settings"].get("preset")
    if isinstance(preset, str):
        prior["settings"]["preset"] = preset_now(preset, prior.get("written", ""))


def write_resume(out: Path, state: bytes, counters: dict) -> Path:
    """Write the library's training state ``state`` as a new file (never replacing one) and then ``resume.json``
    naming it and the day it is written (UTC, ``written``), both atomically: a call killed in between leaves the
    previous resume point intact."""
    from ..atomic import atomic_write_bytes
    from .policy_file import utc_day

    path = Path(out) / "resume" / f"state_call{int(counters['calls'])}.pt"
    if path.exists():
        raise FileExistsError(f"{path} exists; a resume state is never overwritten")
    atomic_write_bytes(path, state, replace=False)  # nor one that appears after the check above
    write_json(Path(out) / "resume.json", {**counters, "state": str(path.relative_to(out)), "written": utc_day()})
    return path


#: The counters ``resume.json`` carries from call to call, out of ``meta`` (:func:`finish_call`).
RESUME_COUNTERS = tuple(name for name in RESUME_FIELDS if name not in ("settings", "state"))


def finish_call(out: Path, args: argparse.Namespace, meta: dict, settings: dict, state: bytes,
                save: Callable[[Path], object], evaluate: Callable[..., dict], interrupted: str | None,
                also_save: Callable[[str], object] | None = None) -> dict:
    """The end of a library recipe's call, in the order that keeps a resume point whatever stops it: the library's
    training ``state`` and ``resume.json`` (:func:`write_resume`, with ``settings`` and ``meta``'s counters), then
    ``policy.pt`` by ``save(path)`` (and the recipe's own files by ``also_save(tag)``, ``tag`` naming this call for
    :func:`keep_previous`), then unless ``interrupted`` (what stopped the call) or ``--eval_envs 0`` the
    gait test ``evaluate(policy, out_dir, num_envs=, device=, seconds=, test=)`` (``--eval_test``; the robust test's
    report is printed), then ``result.json``. A resumed call keeps the earlier call's files (:func:`keep_previous`).
    ``meta["calls"]`` is this call's count; returns ``result`` (``{"train": meta, "eval": ... or "interrupted":
    ...}``)."""
    calls = int(meta["calls"]) - 1  # earlier calls: their files get this tag
    write_resume(out, state, {"settings": settings, **{k: meta[k] for k in RESUME_COUNTERS}})
    save(keep_previous(out / "policy.pt", f"call{calls}"))
    if also_save is not None:
        also_save(f"call{calls}")
    result = {"train": meta}
    if interrupted is not None:
        result["interrupted"] = interrupted
    elif args.eval_envs > 0:
        folder = keep_previous(out / "eval", f"call{calls}")
        result["eval"] = evaluate(out / "policy.pt", folder, num_envs=args.eval_envs, device=args.device,
                                  seconds=args.eval_seconds, test=args.eval_test)
        if args.eval_test == "robust":
            from ..evaluation.robust import robust_report_text

            print(robust_report_text(result["eval"], folder), flush=True)
    write_json(keep_previous(out / "result.json", f"call{calls}"), result)
    return result


def eval_text(result: dict):
    """What a recipe's last line says of its gait test: the standard test's summary, the robust test's verdict (its
    report, printed by :func:`finish_call`, has the rest), or ``"skipped"``."""
    report = result.get("eval", "skipped")
    if isinstance(report, dict) and report.get("test") == "robust":
        return f"robust, {'walks' if report['passes'] else 'does not walk yet'} (report above)"
    return report


def keep_previous(path: Path, tag: str) -> Path:
    """Before a resumed call writes ``path`` again (``policy.pt``, ``eval/``), rename the earlier one to
    ``<stem>_<tag><suffix>`` so that nothing a previous call wrote is overwritten; returns the free ``path``."""
    path = Path(path)
    if path.exists():
        kept = path.with_name(f"{path.stem}_{tag}{path.suffix}")
        if kept.exists():
            raise FileExistsError(f"{kept} exists; refusing to overwrite an earlier call's output")
        path.rename(kept)
    return path


def fresh_dir(path: Path) -> Path:
    """``path``, or ``path_2``, ``path_3``, ... if taken (a log folder a killed call left): never shared."""
    path, k = Path(path), 2
    candidate = path
    while candidate.exists():
        candidate, k = path.with_name(f"{path.name}_{k}"), k + 1
    return candidate


class TimeUp(Exception):
    """Raised from inside a library's training loop when the recipe's ``--max_minutes`` are spent."""


def stop_on_signals(clock: TrainingClock) -> contextlib.AbstractContextManager[None]:
    """While training: the first SIGINT (Ctrl-C) or SIGTERM asks ``clock`` to raise :class:`Interrupted` at the next
    env step, where the rollout in progress is discarded as at :class:`TimeUp` and no update is cut short; a second
    one raises ``KeyboardInterrupt`` at once (the recipes save then too, with the update in progress possibly part
    applied). The previous handlers are back on exit. Python delivers signals to the main thread only, so elsewhere
    nothing is installed. (:func:`tocabi_torchrl.rl.interrupt.stop_on_signals`, which ``ppo_walk`` uses too.)"""
    return _stop_on_signals(clock, "stopping at the next env step to save the resume state")


def report_interruption(name: str, stop: BaseException, out: Path) -> str:
    """Print that the call of recipe ``name`` was interrupted by ``stop`` and that its resume state is being saved;
    returns what stopped it (a signal's name or the exception's), for ``result.json``."""
    reason = str(stop) or type(stop).__name__
    print(f"{name}: interrupted ({reason}); saving the resume state and policy.pt in {out}, skipping the gait test. "
          f"To continue, run the same command with --resume (--max_minutes, if given, caps the total)",
          file=sys.stderr, flush=True)
    return reason


def run_call(name: str, clock: TrainingClock, out: Path, learn: Callable[[], object], left: int,
             done: str) -> tuple[bool, str | None]:
    """Train one call of recipe ``name``: ``learn()`` unless the clock's time is up or ``left`` (iterations or steps
    to go) is not positive (then says so, with ``done``: what earlier calls did), under :func:`stop_on_signals`.
    The clock's :class:`TimeUp` and Ctrl-C/SIGTERM end it alike, the call then saved by the recipe as usual. Returns
    whether training stopped early (the rollout in progress is then discarded) and what interrupted it, if a signal
    did (for ``result.json``)."""
    with stop_on_signals(clock):
        try:
            if clock.time_up or left <= 0:
                print(f"{name}: nothing left to train ({clock.elapsed:.0f} s, {done} done)")
            else:
                learn()
        except TimeUp as stop:
            print(f"{name}: {stop}")
            return True, None
        except (Interrupted, KeyboardInterrupt) as stop:  # saved as at TimeUp: the call can be resumed
            return True, report_interruption(name, stop, out)
    return False, None


class TrainingClock:
    """A step hook (``TensorStepper.step_hooks``) that saves the policy at every ``checkpoint_minutes`` of training
    wall-clock (``<out>/checkpoints/wall_XXXXXs.pt``, what the per-library table gait-tests) and raises
    :class:`TimeUp` after ``max_minutes`` (0 = off for either). ``save(path)`` writes the current policy. The names
    are whole seconds (``config.wall_tag``), so a ``checkpoint_minutes`` under 1/60 (1 s) is a ``ValueError``.

    ``offset``: training seconds of earlier calls of a resumed run; :attr:`elapsed`, the snapshot names and the
    limit are then cumulative (a resumed run's first snapshot is the next multiple of ``checkpoint_minutes``)."""

    def __init__(self, out: Path, save, max_minutes: float = 0.0, checkpoint_minutes: float = 0.0,
                 offset: float = 0.0, snapshots: list[str] | None = None):
        import math
        import time

        self._time = time.perf_counter
        self.start = self._time()
        self.offset = float(offset)
        self.out, self.save = Path(out), save
        check_snapshot_minutes(checkpoint_minutes)
        self.limit = 60.0 * max_minutes
        self.every = 60.0 * checkpoint_minutes
        self.next = (math.floor(self.offset / self.every) + 1) * self.every if self.every > 0 else 0.0
        self.snapshots: list[str] = list(snapshots or [])
        #: The signal that asked training to stop (:func:`stop_on_signals`); :class:`Interrupted` at the next call.
        self.stop_signal: str | None = None

    @property
    def elapsed(self) -> float:
        """Training seconds: those of earlier calls plus those since this clock started."""
        return self.offset + self._time() - self.start

    def freeze(self) -> float:
        """Stop the clock (training is over; saving and testing are not training time); returns :attr:`elapsed`."""
        now = self.elapsed
        self.offset, self._time = now, (lambda: self.start)
        return now

    @property
    def time_up(self) -> bool:
        """Whether ``max_minutes`` are already spent (a resumed run that has nothing left to train)."""
        return self.limit > 0 and self.elapsed >= self.limit

    def __call__(self) -> None:
        if self.stop_signal is not None:
            raise Interrupted(self.stop_signal)
        elapsed = self.elapsed
        if self.every > 0 and elapsed >= self.next:
            path = self.out / "checkpoints" / f"{wall_tag(self.next)}.pt"
            if str(path) in self.snapshots:  # check_snapshot_minutes rules this out; never let one replace another
                raise RuntimeError(f"{path} is already one of this run's snapshots; the mark at {self.next:g} s "
                                   "would replace it (snapshot period under 1 s?)")
            if path.exists():  # left by a call killed before it saved its resume state: keep it aside
                keep_previous(path, f"unresumed{len(list(path.parent.glob(path.stem + '_unresumed*')))}")
            self.save(path)
            self.snapshots.append(str(path))
            self.next += self.every
        if self.limit > 0 and elapsed >= self.limit:
            raise TimeUp(f"--max_minutes {self.limit / 60:g} reached after {elapsed:.0f} s")
