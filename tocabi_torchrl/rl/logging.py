"""Run logging: CSV under ``runs/<name>/`` (always, works offline), TensorBoard and wandb on request, a progress bar."""

from __future__ import annotations

import csv
import importlib.util
import json
import math
import os
from pathlib import Path

from .atomic import atomic_write_text

__all__ = ["RunLogger", "require_loggers", "write_config"]

#: The package each optional logger imports, and how to install it.
_LOGGER_PACKAGES = {
    "wandb": ("wandb", 'pip install "tocabi-torchrl[wandb]"'),
    "tensorboard": ("tensorboard", "pip install tensorboard"),
}


def require_loggers(loggers) -> None:
    """Raise ``ModuleNotFoundError`` with the install command if a requested logger's package is missing (checked
    before the run starts, without importing it)."""
    for name in loggers:
        if name in _LOGGER_PACKAGES:
            module, install = _LOGGER_PACKAGES[name]
            if importlib.util.find_spec(module) is None:
                raise ModuleNotFoundError(f"--loggers {name} needs the '{module}' package, which is not installed: "
                                          f"{install} (or drop {name} from --loggers)", name=module)


def write_config(run_dir: str | os.PathLike, cfg) -> Path:
    """Write ``config.json`` (the run's config tree plus the checkpoint ``schema_version``) atomically."""
    from .checkpoint import SCHEMA_VERSION

    return atomic_write_text(Path(run_dir) / "config.json",
                             json.dumps({"schema_version": SCHEMA_VERSION, **cfg.to_dict()}, indent=2, default=str))


def _shown(value, fmt: str) -> str:
    """``value`` formatted, or ``-`` while it is unknown (NaN: no episode has ended yet)."""
    return "-" if value is None or (isinstance(value, float) and math.isnan(value)) else format(value, fmt)


class RunLogger:
    """Writes one row of metrics per logged iteration to ``metrics.csv`` (columns fixed by the first row, or by the
    existing file when a run is resumed) and forwards the same numbers to TensorBoard / wandb when ``cfg.loggers``
    asks for them."""

    def __init__(self, run_dir: Path, cfg, total_iterations: int, start_iteration: int = 0):
        require_loggers(cfg.loggers)
        self.run_dir = Path(run_dir)
        self.run_dir.mkdir(parents=True, exist_ok=True)
        write_config(self.run_dir, cfg)
        self.csv_path = self.run_dir / "metrics.csv"
        self._file = None
        self._writer = None
        self._columns: list[str] | None = None
        self._tb = None
        self._wandb = None
        # Episodes outlast several iterations: the bar shows the last finished episodes' numbers until new ones end.
        self._last_episode = {"episode_return": None, "episode_length": None}
        if "tensorboard" in cfg.loggers:
            from torch.utils.tensorboard import SummaryWriter

            self._tb = SummaryWriter(str(self.run_dir / "tensorboard"))
        if "wandb" in cfg.loggers:
            import wandb

            mode = "online" if os.environ.get("WANDB_API_KEY") else "offline"
            self._wandb = wandb.init(project="tocabi-torchrl", name=cfg.name, config=cfg.to_dict(),
                                     dir=str(self.run_dir), mode=mode)
        self._bar = None
        if cfg.progress_bar:
            from tqdm.auto import tqdm

            self._bar = tqdm(total=total_iterations, initial=start_iteration, unit="it", dynamic_ncols=True)

    def _open_csv(self, row: dict) -> None:
        columns = list(row)
        existing = self.csv_path.exists() and self.csv_path.stat().st_size > 0
        if existing:  # a resumed run continues the file under its header
            with open(self.csv_path, newline="") as f:
                columns = next(csv.reader(f), None) or columns
        self._file = open(self.csv_path, "a", newline="")
        self._columns = columns
        self._writer = csv.DictWriter(self._file, fieldnames=self._columns, extrasaction="ignore")
        if not existing:
            self._writer.writeheader()

    def log(self, iteration: int, metrics: dict) -> None:
        row = {"iteration": iteration, **metrics}
        if self._writer is None:
            self._open_csv(row)
        self._writer.writerow(row)
        self._file.flush()
        if self._tb is not None:
            for key, value in metrics.items():
                self._tb.add_scalar(key, value, iteration)
        if self._wandb is not None:
            self._wandb.log(row, step=iteration)
        for key in self._last_episode:
            value = metrics.get(key)
            if value is not None and not math.isnan(value):
                self._last_episode[key] = value
        ret, length = _shown(self._last_episode["episode_return"], ".1f"), \
            _shown(self._last_episode["episode_length"], ".0f")
        if self._bar is not None:
            self._bar.n = iteration
            self._bar.set_postfix(ret=ret, len=length, sps=f"{metrics.get('env_steps_per_s', 0):,.0f}", refresh=False)
            self._bar.refresh()
        else:
            print(f"it {iteration}: return {ret} len {length} {metrics.get('env_steps_per_s', 0):,.0f} steps/s",
                  flush=True)

    def close(self) -> None:
        if self._file is not None:
            self._file.close()
        if self._tb is not None:
            self._tb.close()
        if self._wandb is not None:
            self._wandb.finish()
        if self._bar is not None:
            self._bar.close()
