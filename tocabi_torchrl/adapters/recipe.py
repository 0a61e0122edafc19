"""What the library recipes (``recipes/train_<library>.py``) share: their common options and the output folder."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from ..rl.atomic import atomic_write_text

__all__ = ["TimeUp", "TrainingClock", "base_parser", "open_out_dir", "write_json"]


def base_parser(description: str, num_envs: int, iterations: int) -> argparse.ArgumentParser:
    """Options every library recipe takes: envs, device, iteration budget, seed, output folder, gait test size."""
    parser = argparse.ArgumentParser(description=description)
    parser.add_argument("--num_envs", type=int, default=num_envs, help=f"robots simulated at once (default: {num_envs})")
    parser.add_argument("--device", default="auto", help="auto (CUDA if present, else cpu), cpu, cuda or cuda:N")
    parser.add_argument("--iterations", type=int, default=iterations,
                        help=f"PPO iterations (rollout + update) to train (default: {iterations})")
    parser.add_argument("--max_minutes", type=float, default=0.0,
                        help="stop after this many minutes of training (0 = no limit)")
    parser.add_argument("--checkpoint_minutes", type=float, default=0.0,
                        help="also save the policy every this many minutes of training (0 = off)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the env and the library (default: 0)")
    parser.add_argument("--preset", default="default", help="task preset of tocabi_torchrl.rl.config (default: default)")
    parser.add_argument("--out", required=True, help="output folder; must not exist yet (runs are never overwritten)")
    parser.add_argument("--eval_envs", type=int, default=256, help="robots in the final 8 s gait test (0 = skip it)")
    parser.add_argument("--eval_seconds", type=float, default=8.0, help="length of the gait test [s] (default: 8)")
    return parser


def open_out_dir(path: str) -> Path:
    """Create the run's output folder; ``SystemExit`` with a message if it exists (an earlier run is kept)."""
    out = Path(path)
    if out.exists():
        raise SystemExit(f"error: {out} exists; pass another --out (an earlier run is never overwritten)")
    out.mkdir(parents=True)
    return out


def write_json(path: Path, data: dict) -> None:
    atomic_write_text(path, json.dumps(data, indent=2))


class TimeUp(Exception):
    """Raised from inside a library's training loop when the recipe's ``--max_minutes`` are spent."""


class TrainingClock:
    """A step hook (``TensorStepper.step_hooks``) that saves the policy at every ``checkpoint_minutes`` of training
    wall-clock (``<out>/checkpoints/wall_XXXXXs.pt``, what the per-library table gait-tests) and raises
    :class:`TimeUp` after ``max_minutes`` (0 = off for either). ``save(path)`` writes the current policy."""

    def __init__(self, out: Path, save, max_minutes: float = 0.0, checkpoint_minutes: float = 0.0):
        import time

        self._time = time.perf_counter
        self.start = self._time()
        self.out, self.save = Path(out), save
        self.limit = 60.0 * max_minutes
        self.every = 60.0 * checkpoint_minutes
        self.next = self.every
        self.snapshots: list[str] = []

    @property
    def elapsed(self) -> float:
        """Seconds since the clock started."""
        return self._time() - self.start

    def __call__(self) -> None:
        elapsed = self.elapsed
        if self.every > 0 and elapsed >= self.next:
            path = self.out / "checkpoints" / f"wall_{int(self.next):05d}s.pt"
            self.save(path)
            self.snapshots.append(str(path))
            self.next += self.every
        if self.limit > 0 and elapsed >= self.limit:
            raise TimeUp(f"--max_minutes {self.limit / 60:g} reached after {elapsed:.0f} s")
