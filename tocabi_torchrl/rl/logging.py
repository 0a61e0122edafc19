"""Run logging: torchrl's loggers behind one object (:class:`RunLogger`), and the progress shown while training.

Each logged iteration's metrics go to :mod:`torchrl.record.loggers` instances, ``step`` = the iteration, all with
``log_dir`` = the run folder:

- ``CSVLogger`` (exp_name ``metrics``), always, whatever ``--loggers`` says: it needs no package and no network, and
  the package's own tools read it (curves, benchmarks, the resume's cut back to the checkpoint). It writes one file
  per scalar, ``<run>/metrics/scalars/<name>.csv`` with ``iteration,value`` lines, opened for appending, so a
  resumed run continues the same files (:func:`~tocabi_torchrl.rl.run_dir.open_run` first drops what was logged
  after the checkpoint). Read them with :func:`~tocabi_torchrl.rl.metrics_files.read_metrics`, the one reader.
- ``TensorboardLogger`` (exp_name ``tensorboard``) on ``--loggers tensorboard``: event files in
  ``<run>/tensorboard/``; a resumed run adds a new event file beside the earlier ones, which starts by telling
  TensorBoard to drop the earlier files' events after the checkpoint (what a killed run logged past it).
- ``WandbLogger`` on ``--loggers wandb``: project ``tocabi-torchrl``, the run's name and config, files in
  ``<run>/wandb/``. Offline (``mode="offline"`` passed to ``wandb.init``, not the process-wide ``WANDB_MODE`` that
  torchrl's ``offline=True`` sets) unless ``WANDB_API_KEY`` is set. The W&B run id is kept in
  ``<run>/wandb_run_id``, so a resumed run goes on in the same W&B run. W&B keeps every row it was sent: the rows a
  killed run logged after its checkpoint stay there, and the resumed run logs those iterations again (two rows per
  ``step``; docs/training.md, "Loggers", says what to do). Delete the id file before resuming for a new W&B run.

A requested logger whose package is missing is refused before the run starts (:func:`require_loggers`), with the
command that installs it. In a data-parallel run only rank 0 makes a :class:`RunLogger` (the trainer's choice).
"""

from __future__ import annotations

import importlib.util
import json
import math
import os
import sys
from pathlib import Path

from ..atomic import atomic_write_text
from .metrics_files import METRICS_DIR

__all__ = ["RunLogger", "keep_edited_config", "make_loggers", "print_line", "require_loggers", "write_config"]

#: The package each optional logger imports, and how to install it.
_LOGGER_PACKAGES = {
    "wandb": ("wandb", 'pip install -e ".[wandb]" in the repository'),
    "tensorboard": ("tensorboard", "pip install tensorboard"),
}
#: The W&B project of the runs.
WANDB_PROJECT = "tocabi-torchrl"
#: The file in a run folder that keeps its W&B run id.
WANDB_ID_FILE = "wandb_run_id"


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


def keep_edited_config(run_dir: str | os.PathLike, cfg) -> Path | None:
    """Before a resumed run writes ``config.json`` again: if the file was edited (an option a resume may not change
    holds another value than the checkpoint's config, or the file no longer reads as a config: broken JSON, an
    unknown option), move it to a free ``config.edited[.N].json`` and say so; a resume trains the checkpoint's
    config, and rewriting the file would silently drop the edit. Returns the new path,
    or None when nothing was edited."""
    from ..config import config_from_dict
    from .resume import _differences

    path = Path(run_dir) / "config.json"
    try:
        text = path.read_text()
    except OSError:  # none (or unreadable): no edit to keep
        return None
    try:
        # Read as a checkpoint's config is: older files' renamed or missing options are not taken for edits.
        edited = _differences(config_from_dict(json.loads(text)), cfg)  # (path, in the file, the run's)
    except (ValueError, TypeError, AttributeError) as err:  # an edit that broke the file, or an unknown option
        what = f"does not read as a run config ({str(err).splitlines()[0][:200]})"
    else:
        if not edited:
            return None
        shown = ", ".join(f"{k}: {was!r} (the run's: {now!r})" for k, was, now in edited[:3])
        what = f"was edited ({shown}{f' and {len(edited) - 3} more' if len(edited) > 3 else ''})"
    kept, n = path.with_name("config.edited.json"), 1
    while kept.exists():
        kept, n = path.with_name(f"config.edited.{n}.json"), n + 1
    os.replace(path, kept)
    print(f"{path} {what}; a resume trains the checkpoint's config and ignores the file, so the file was moved to "
          f"{kept.name} and config.json is written again. Options a resume may change go on the command line; for "
          "other changes start a new run (--name NEW).", flush=True)
    return kept


def make_loggers(run_dir: str | os.PathLike, cfg, resumed_at: int = 0) -> dict:
    """The torchrl loggers of a run folder, by name: ``csv`` always, then those of ``cfg.loggers`` (see the module
    docstring for where each writes). Checks the packages first (:func:`require_loggers`). ``resumed_at``: the
    checkpoint's iteration a resumed run goes on from (0: a new run); TensorBoard then drops the earlier event files'
    steps after it, as :func:`~tocabi_torchrl.rl.metrics_files.trim_metrics` drops those rows from the CSV files."""
    from torchrl.record.loggers import CSVLogger

    require_loggers(cfg.loggers)
    run_dir = Path(run_dir)
    loggers = {"csv": CSVLogger(exp_name=METRICS_DIR, log_dir=str(run_dir))}
    if "tensorboard" in cfg.loggers:
        from torchrl.record.loggers import TensorboardLogger

        loggers["tensorboard"] = (TensorboardLogger(exp_name="tensorboard", log_dir=str(run_dir)) if resumed_at <= 0
                                  else _resumed_tensorboard(run_dir, resumed_at))
    if "wandb" in cfg.loggers:
        loggers["wandb"] = _wandb_logger(run_dir, cfg)
    return loggers


def _resumed_tensorboard(run_dir: Path, resumed_at: int):
    """torchrl's TensorBoard logger whose writer has ``purge_step`` (the first step after the checkpoint): event files
    are append-only, so the steps a killed run logged past its checkpoint can only be purged on reading."""
    from torch.utils.tensorboard import SummaryWriter
    from torchrl.record.loggers import TensorboardLogger

    class ResumedTensorboardLogger(TensorboardLogger):
        def _create_experiment(self) -> SummaryWriter:
            return SummaryWriter(log_dir=os.path.join(self.log_dir, self.exp_name), purge_step=resumed_at + 1)

    return ResumedTensorboardLogger(exp_name="tensorboard", log_dir=str(run_dir))


def _wandb_logger(run_dir: Path, cfg):
    from torchrl.record.loggers import WandbLogger

    id_file = run_dir / WANDB_ID_FILE
    run_id = id_file.read_text().strip() if id_file.is_file() else None
    mode = "online" if os.environ.get("WANDB_API_KEY") else "offline"
    logger = WandbLogger(exp_name=cfg.name, log_dir=str(run_dir), project=WANDB_PROJECT, id=run_id, mode=mode,
                         config=cfg.to_dict())
    if run_id is None:
        atomic_write_text(id_file, f"{logger.experiment.id}\n")
    return logger


def _shown(value, fmt: str) -> str:
    """``value`` formatted, or ``-`` while it is unknown (NaN: no episode has ended yet)."""
    return "-" if value is None or (isinstance(value, float) and math.isnan(value)) else format(value, fmt)


def print_line(text: str, file=None) -> None:
    """Print ``text`` on a line of its own to ``file`` (stdout) while training, beside :class:`RunLogger`'s progress
    bar if one is drawn: tqdm clears the bar, writes the line and draws the bar again under it, where a plain print
    lands on the bar's line (``...sps=362]SIGINT: stopping``).

    Fit for a signal handler: it imports nothing (a bar is only drawn once tqdm is imported, so without it a print
    is enough) and tqdm's write lock is re-entrant."""
    file = sys.stdout if file is None else file
    bars = getattr(sys.modules.get("tqdm"), "tqdm", None)
    if bars is None:
        print(text, file=file, flush=True)
        return
    bars.write(text, file=file)
    file.flush()


class RunLogger:
    """The trainer's one logging object: writes ``config.json``, sends each logged iteration's metrics to every
    torchrl logger of :func:`make_loggers` (``self.loggers``) and shows the progress (a bar, or one line per
    logged iteration)."""

    def __init__(self, run_dir: str | os.PathLike, cfg, total_iterations: int, start_iteration: int = 0):
        """``start_iteration``: the iteration the run goes on from (a resumed run's checkpoint; 0: a new run)."""
        require_loggers(cfg.loggers)  # before anything is written
        self.run_dir = Path(run_dir)
        self.run_dir.mkdir(parents=True, exist_ok=True)
        if start_iteration > 0:
            keep_edited_config(self.run_dir, cfg)
        write_config(self.run_dir, cfg)
        self.loggers = make_loggers(self.run_dir, cfg, resumed_at=start_iteration)
        # Episodes outlast several iterations: the bar shows the last finished episodes' numbers until new ones end.
        self._last_episode = {"episode_return": None, "episode_length": None}
        self._bar = None
        if cfg.progress_bar:
            from tqdm.auto import tqdm

            self._bar = tqdm(total=total_iterations, initial=start_iteration, unit="it", dynamic_ncols=True)

    def log(self, iteration: int, metrics: dict) -> None:
        """Log ``metrics`` (name -> number) at ``iteration`` to every logger, then show the progress."""
        for logger in self.loggers.values():
            # One call per iteration: CSV and TensorBoard log each scalar (log_scalar), W&B one history row.
            logger.log_metrics(metrics, step=iteration)
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
        """Flush and close every logger (and the bar); the CSV files and the bar are closed even if a logger fails."""
        try:
            for logger in self.loggers.values():
                logger.close()
        finally:
            # torchrl's CSV experiment has no close of its own: its files would stay open until it is collected.
            for file in self.loggers["csv"].experiment.files.values():
                file.close()
            if self._bar is not None:
                self._bar.close()
