"""Run logging: CSV under ``runs/<name>/`` (always, works offline), TensorBoard and wandb on request, a progress bar."""

from __future__ import annotations

import csv
import json
import os
from pathlib import Path

__all__ = ["RunLogger"]


class RunLogger:
    """Writes one row of metrics per logged iteration to ``metrics.csv`` (columns fixed by the first row) and
    forwards the same numbers to TensorBoard / wandb when ``cfg.loggers`` asks for them."""

    def __init__(self, run_dir: Path, cfg, total_iterations: int, start_iteration: int = 0):
        self.run_dir = Path(run_dir)
        self.run_dir.mkdir(parents=True, exist_ok=True)
        (self.run_dir / "config.json").write_text(json.dumps(cfg.to_dict(), indent=2, default=str))
        self.csv_path = self.run_dir / "metrics.csv"
        self._file = None
        self._writer = None
        self._columns: list[str] | None = None
        self._tb = None
        self._wandb = None
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

    def log(self, iteration: int, metrics: dict) -> None:
        row = {"iteration": iteration, **metrics}
        if self._writer is None:
            resume = self.csv_path.exists() and self.csv_path.stat().st_size > 0
            self._file = open(self.csv_path, "a", newline="")
            self._columns = list(row)
            self._writer = csv.DictWriter(self._file, fieldnames=self._columns, extrasaction="ignore")
            if not resume:
                self._writer.writeheader()
        self._writer.writerow(row)
        self._file.flush()
        if self._tb is not None:
            for key, value in metrics.items():
                self._tb.add_scalar(key, value, iteration)
        if self._wandb is not None:
            self._wandb.log(row, step=iteration)
        if self._bar is not None:
            self._bar.n = iteration
            self._bar.set_postfix(ret=f"{metrics.get('episode_return', float('nan')):.1f}",
                                  len=f"{metrics.get('episode_length', float('nan')):.0f}",
                                  sps=f"{metrics.get('env_steps_per_s', 0):,.0f}", refresh=False)
            self._bar.refresh()
        else:
            print(f"it {iteration}: return {metrics.get('episode_return', float('nan')):.2f} "
                  f"len {metrics.get('episode_length', float('nan')):.0f} "
                  f"{metrics.get('env_steps_per_s', 0):,.0f} steps/s", flush=True)

    def close(self) -> None:
        if self._file is not None:
            self._file.close()
        if self._tb is not None:
            self._tb.close()
        if self._wandb is not None:
            self._wandb.finish()
        if self._bar is not None:
            self._bar.close()
