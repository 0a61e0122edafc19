"""From a command line to the run that actually happens on this machine, and the banner that says so.

Only ``--device auto`` with no ``--preset`` given may turn into something else than asked: without a CUDA GPU it
runs the small ``cpu_smoke`` configuration (keeping the other options given), and the banner says so, as does an
error that the options raise against it. An explicit request this machine cannot honour (``--device cuda`` without
CUDA, a GPU-sized ``--preset`` or resumed run on ``auto``) raises :class:`LaunchError` with what to pass instead.
Under torchrun (``data_parallel``) there is no fallback: a multi-rank launch means GPUs were expected, and no rank
prints a banner that could say the run changed.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

from ..config import RunConfig, preset_config, preset_tree
from .config import PRESETS, given_options, option_value, parse_tree, resume_config

__all__ = ["LaunchError", "CPU_SIZED_PRESETS", "CPU_WORLDS", "launch_config", "banner", "cpu_size_note"]

#: Presets that run in minutes on a CPU; every other preset is sized for a GPU.
CPU_SIZED_PRESETS = frozenset({"cpu_smoke"})
#: The most worlds a run on the CPU gets without a note: beyond, an iteration takes minutes (the default preset's
#: 4,096 envs × 48 steps took about 5 minutes per iteration on 2 cores).
CPU_WORLDS = 64


class LaunchError(ValueError):
    """An explicit request (device, preset) that this machine cannot honour."""


def launch_config(argv: Sequence[str] | None, cuda_available: bool, description: str = "",
                  data_parallel: bool = False, prog: str | None = None) -> tuple[RunConfig, dict, str | None]:
    """Parse ``argv`` (see :mod:`tocabi_torchrl.rl.config`) into the validated config to run on this machine.

    Returns the config, the options ``argv`` names (``{path: value}``) and, when the run differs from the request, a
    note saying why. The fallback is decided before the options are applied, so options sized for the smoke run
    (e.g. ``--env.num_envs 4``) are checked against it rather than against the GPU preset. ``data_parallel`` (a
    torchrun launch) refuses the fallback instead of taking it.
    """
    argv = list(argv or [])
    resume = option_value(argv, "resume")
    if resume:
        resumed, given = resume_config(resume, argv, prog, description)
    asked = option_value(argv, "preset")
    if asked is not None and asked not in PRESETS:
        raise LaunchError(f"--preset {asked}: unknown preset; choose one of {', '.join(sorted(PRESETS))}")
    preset = resumed.preset if resume else (asked or "default")
    device = resumed.device if resume else (option_value(argv, "device") or "auto")
    note, base = None, {}
    if not cuda_available:
        if device.startswith("cuda") and resume and option_value(argv, "device") is None:
            raise LaunchError(f"the resumed run {resume} was trained with --device {device}, and torch sees no CUDA "
                              "GPU on this machine; pass --device cpu to continue it on the CPU")
        if device.startswith("cuda"):
            # A resume never falls back to the smoke run: leaving --device out there means the run's saved device.
            instead = ("to continue the run on the CPU" if resume else
                       "(or leave --device out for the small CPU smoke run)")
            raise LaunchError(f"--device {device} was requested but torch sees no CUDA GPU on this machine; pass "
                              f"--device cpu {instead}")
        if device == "auto" and data_parallel:
            raise LaunchError("torchrun started several ranks but torch sees no CUDA GPU on this machine; pass "
                              "--device cpu for a data-parallel run on the CPU (gloo), with --preset cpu_smoke for the"
                              " small one")
        if device == "auto" and preset not in CPU_SIZED_PRESETS:
            sized = preset_config(preset)
            gpu_sized = f"sized for a GPU ({sized.env.num_envs:,} envs, {sized.total_env_steps:,} env steps)"
            if resume:
                raise LaunchError(f"the resumed run {resume} uses preset {preset!r}, {gpu_sized}, and torch sees "
                                  "no CUDA GPU; pass --device cpu to continue it on the CPU anyway")
            if asked is not None:
                raise LaunchError(f"--preset {preset} is {gpu_sized}, and torch sees no CUDA GPU; at its size a CPU "
                                  f"takes days, so use --preset {min(CPU_SIZED_PRESETS)}, or {cpu_sized_hint(sized)}")
            preset, base = min(CPU_SIZED_PRESETS), {"device": "cpu"}
            # What runs instead, that it will not walk, and where the run that does happens: the same command on a
            # machine with a GPU (a newcomer reads this note only, not docs/training.md).
            note = (f"{fallback_said(preset)}; it proves the pipeline and learns nothing useful (it will not walk). "
                    f"On a machine with a CUDA GPU the same command trains the default preset ({sized.env.num_envs:,} "
                    f"envs, {sized.total_env_steps:,} env steps), which learns to walk. Its size takes days on a "
                    f"CPU; to test a change on it, {cpu_sized_hint(sized)}.")
    if resume:
        return resumed, given, note
    from dataclasses import replace

    cfg = parse_tree(argv, replace(preset_tree(preset), **base), prog, description)
    try:
        cfg.validate()
    except ValueError as err:
        if note is None or _refused_without_fallback(argv, str(err), prog, description):
            raise
        # The sizes refused are the fallback's, which the user never asked for (8 envs, not 4,096): say where
        # they came from. The message is amended in place, so the error keeps its type.
        err.args = (f"{err} ({fallback_said(preset)}; pass --device cpu to keep the default preset's sizes)",
                    *err.args[1:])
        raise
    return cfg, given_options(argv, cfg), note


def _refused_without_fallback(argv: Sequence[str], message: str, prog: str | None, description: str) -> bool:
    """Whether the same options on the default preset with ``--device cpu`` are refused with the same ``message``:
    then the value given is wrong whatever the preset (``--max_minutes -5``), and blaming the fallback's sizes, with
    ``--device cpu`` as the fix, would send the user after the wrong option."""
    from dataclasses import replace

    try:
        parse_tree(argv, replace(preset_tree("default"), device="cpu"), prog, description).validate()
    except ValueError as err:
        return str(err) == message
    return False


def fallback_said(preset: str) -> str:
    """What the run says when ``--device auto`` finds no CUDA GPU and runs ``preset`` instead of the default: the
    start of its note, and the end of an error that the fallback's sizes caused."""
    return (f"No CUDA GPU found and --device auto: running the small CPU smoke configuration (preset {preset}) "
            "instead of the GPU-sized default")


def cpu_sized_hint(cfg: RunConfig) -> str:
    """How the preset of ``cfg`` runs on a CPU at a size that ends (docs/training.md, "On a CPU"): 8 envs, a
    mini-batch that divides their rollout, ten iterations (one of a rollout longer than 1,000 steps), a short test.

    >>> from tocabi_torchrl.config import preset_config
    >>> cpu_sized_hint(preset_config("default")).split(" --eval")[0]
    'pass --device cpu --env.num_envs 8 --ppo.minibatch_size 96 --total_env_steps 3840'
    >>> cpu_sized_hint(preset_config("reference")).split(" --eval")[0]  # 8 envs, 128 divides 16,384 already
    'pass --device cpu --total_env_steps 16384'
    """
    envs = min(8, cfg.env.num_envs)
    frames = envs * cfg.ppo.steps_per_env
    options = ["--device cpu"]
    if envs != cfg.env.num_envs:
        options.append(f"--env.num_envs {envs}")
    if cfg.ppo.minibatch_size > frames or frames % cfg.ppo.minibatch_size:
        options.append(f"--ppo.minibatch_size {frames // 4 if frames % 4 == 0 else frames}")
    options.append(f"--total_env_steps {frames * (10 if frames <= 1000 else 1)}")
    return f"pass {' '.join(options)} --eval_envs 2 --eval_seconds 1 (docs/training.md: On a CPU)"


def cpu_size_note(cfg: RunConfig, device) -> str | None:
    """A note for a run of more than :data:`CPU_WORLDS` envs on the CPU (``device``: a ``torch.device`` or its
    name), or None: asked for explicitly (``--device cpu``), it runs as asked, but its progress bar first moves after
    an iteration of minutes, and a user who expected seconds should hear why and how to run a size that ends.

    >>> from tocabi_torchrl.config import preset_config
    >>> cpu_size_note(preset_config("default"), "cpu").split(" takes")[0]
    'note: 4,096 envs on the CPU: each iteration of 196,608 env steps'
    >>> cpu_size_note(preset_config("default"), "cuda") is None, cpu_size_note(preset_config("cpu_smoke"), "cpu")
    (True, None)
    """
    if getattr(device, "type", str(device).split(":")[0]) != "cpu" or cfg.env.num_envs <= CPU_WORLDS:
        return None
    return (f"note: {cfg.env.num_envs:,} envs on the CPU: each iteration of {cfg.frames_per_batch:,} env steps takes "
            "minutes (the progress bar moves once per iteration); to test a change, "
            f"{cpu_sized_hint(cfg).replace('--device cpu ', '')}")


def banner(cfg: RunConfig, given: dict, device) -> str:
    """One line saying what will run: preset, size, budget, device and the options given on the command line; a
    second, ``note: ...``, when the mini-batch size leaves part of each epoch out (:meth:`RunConfig.minibatch_note`)."""
    given = {k: v for k, v in given.items() if k != "preset"}
    shown = ", ".join(f"{k}={','.join(map(str, v)) if isinstance(v, tuple) else v}" for k, v in given.items())
    return (f"training {cfg.name}: preset {cfg.preset}, {cfg.env.num_envs:,} envs, {cfg.iterations:,} iterations of "
            f"{cfg.frames_per_batch:,} env steps ({cfg.env.control.mode} control) on {device}"
            + (f"; options given: {shown}" if shown else "")
            + f"; run folder {Path(cfg.run_dir) / cfg.name}"
            + (f"\nnote: {note}" if (note := cfg.minibatch_note()) else ""))
