r"""The log of a training run: the loss of every optimizer step and the
training and validation loss of every epoch, as CSV files, as TensorBoard
event files when :obj:`tensorboard` is installed, and as a figure."""
import csv
import importlib.util
import math
from pathlib import Path
from typing import Dict, List, Optional, Sequence, Union

from tg_nebp.io import atomic_write

__all__ = ['TrainingLog', 'read_training_log']

STEP_FIELDS = ('epoch', 'step', 'loss')
EPOCH_FIELDS = ('epoch', 'train_loss', 'val_loss')


def _read_rows(path: Path, fields) -> List[Dict[str, float]]:
    # a row cut short by a killed run is skipped, not an error; a file that
    # is not text CSV is an error that names it
    if not path.exists():
        return []
    rows = []
    try:
        with open(path, newline='', encoding='utf-8') as f:
            for row in csv.DictReader(f):
                try:
                    rows.append({k: float(row[k]) for k in fields})
                except (KeyError, TypeError, ValueError):
                    continue
    except (UnicodeDecodeError, csv.Error) as e:
        raise ValueError(f"'{path}' is not a training log CSV ({e}); remove "
                         f"it or use another log folder") from None
    return rows


def _same(a: float, b: float) -> bool:
    return a == b or (math.isnan(a) and math.isnan(b))


def _kept_steps(log_dir: Path, history: List[Dict[str, float]]
                ) -> List[Dict[str, float]]:
    # the step rows of a resumed run: those of its finished epochs, as long
    # as the log's epoch rows are this run's (the checkpoint's history);
    # another run's log is an error, not rows mixed into this one
    logged = read_training_log(log_dir)
    for row in logged['epochs']:
        epoch = int(row['epoch'])
        if epoch >= len(history):
            continue  # the interrupted epoch's, trained again
        mine = history[epoch]
        if not all(_same(row[k], float(mine[k])) for k in EPOCH_FIELDS):
            raise ValueError(
                f"the log in '{log_dir}' is another run's: its epoch {epoch} "
                f"({row}) is not the checkpoint's ({mine}); resume with the "
                f"run's own log folder, or use a new one")
    verified = {int(row['epoch']) for row in logged['epochs']}
    return [row for row in logged['steps'] if int(row['epoch']) in verified
            and row['epoch'] < len(history)]


def _write_rows(path: Path, fields, rows: List[Dict[str, float]]):
    def write(tmp):
        with open(tmp, 'w', newline='') as f:
            writer = csv.writer(f)
            writer.writerow(fields)
            writer.writerows([[_cell(row[k]) for k in fields]
                              for row in rows])

    atomic_write(path, write)


def _cell(value: float) -> str:
    return str(int(value)) if float(value).is_integer() else repr(value)


def read_training_log(log_dir: Union[str, Path]
                      ) -> Dict[str, List[Dict[str, float]]]:
    r"""The rows of :obj:`log_dir/steps.csv` (:obj:`"epoch", "step",
    "loss"`) and :obj:`log_dir/epochs.csv` (:obj:`"epoch", "train_loss",
    "val_loss"`) as :obj:`{"steps": [...], "epochs": [...]}`."""
    log_dir = Path(log_dir)
    return dict(steps=_read_rows(log_dir / 'steps.csv', STEP_FIELDS),
                epochs=_read_rows(log_dir / 'epochs.csv', EPOCH_FIELDS))


class TrainingLog:
    r"""Records a run of :func:`~tg_nebp.training.train` in
    :obj:`log_dir`: pass its :obj:`step` method as the :obj:`progress`
    hook and its :obj:`epoch` method as the :obj:`on_epoch` hook.

    * :obj:`steps.csv`: :obj:`epoch, step, loss` after every optimizer step
      (step counts from 1 within the epoch; the loss is per agent and time
      step, in :math:`\text{m}^2`), appended and flushed at once, so that
      it can be followed while training runs;
    * :obj:`epochs.csv`: :obj:`epoch, train_loss, val_loss` after every
      epoch, written atomically;
    * TensorBoard event files (tags :obj:`loss/train_step`,
      :obj:`loss/train_epoch`, :obj:`loss/validation`; the global step is
      the optimizer step, an epoch's values sit at its last step) when
      :obj:`tensorboard` is installed (:obj:`pip install
      tg_nebp[tensorboard]`);
    * :obj:`history.png`, both curves against the epoch, on :meth:`close`.

    A run resumed from a checkpoint passes the checkpoint's
    :obj:`history`: the log keeps the finished epochs' step rows and events
    (and takes their epoch rows from the history, so that a model trained
    without a log still gets its epochs drawn) and drops those of the
    interrupted epoch, which the resumed run trains again. The log's epoch
    rows must be the history's: another run's log is a
    :class:`ValueError`, and step rows of epochs that the log does not
    show finished are dropped, so that two runs never mix. A new run
    (empty :obj:`history`) replaces what the folder holds.

    Args:
        log_dir (str or Path): The folder (created if needed).
        steps_per_epoch (int): Optimizer steps per epoch (batches times time
            steps), for the global step.
        history (sequence of dict, optional): The finished epochs
            (:obj:`{"epoch", "train_loss", "val_loss"}`) of the run that is
            resumed; empty starts a new log. (default: :obj:`()`)
        tensorboard (bool, optional): Write TensorBoard event files;
            :obj:`None` writes them if :obj:`tensorboard` is installed.
            (default: :obj:`None`)
    """

    def __init__(self, log_dir: Union[str, Path], steps_per_epoch: int,
                 history: Sequence[dict] = (),
                 tensorboard: Optional[bool] = None):
        if steps_per_epoch < 1:
            raise ValueError(f"'steps_per_epoch' must be positive, got "
                             f"{steps_per_epoch}")
        self.log_dir = Path(log_dir)
        self.steps_per_epoch = steps_per_epoch
        self.log_dir.mkdir(parents=True, exist_ok=True)
        epochs_done = len(history)
        self.epochs = [{k: entry[k] for k in EPOCH_FIELDS}
                       for entry in history]
        # a new run starts a new log without reading what the folder holds
        steps = (_kept_steps(self.log_dir, self.epochs) if epochs_done
                 else [])
        _write_rows(self.log_dir / 'steps.csv', STEP_FIELDS, steps)
        _write_rows(self.log_dir / 'epochs.csv', EPOCH_FIELDS, self.epochs)
        self._steps = open(self.log_dir / 'steps.csv', 'a', newline='')
        self._step_writer = csv.writer(self._steps)
        if tensorboard is None:
            tensorboard = importlib.util.find_spec('tensorboard') is not None
        self.tensorboard = bool(tensorboard)
        self._writer = None
        if tensorboard:
            from torch.utils.tensorboard import SummaryWriter

            # events at or after the interrupted epoch's first step go
            self._writer = SummaryWriter(
                str(self.log_dir),
                purge_step=(epochs_done * steps_per_epoch + 1
                            if epochs_done else None))

    def step(self, info: dict):
        r"""Records :obj:`{"epoch", "step", "loss"}` of one optimizer
        step (the :obj:`progress` hook of
        :func:`~tg_nebp.training.train`)."""
        row = dict(epoch=info['epoch'], step=info['step'], loss=info['loss'])
        self._step_writer.writerow([_cell(row[k]) for k in STEP_FIELDS])
        self._steps.flush()
        if self._writer is not None:
            self._writer.add_scalar(
                'loss/train_step', row['loss'],
                row['epoch'] * self.steps_per_epoch + row['step'])

    def epoch(self, entry: dict):
        r"""Records :obj:`{"epoch", "train_loss", "val_loss"}` of one epoch
        (the :obj:`on_epoch` hook of :func:`~tg_nebp.training.train`)."""
        self.epochs.append({k: entry[k] for k in EPOCH_FIELDS})
        _write_rows(self.log_dir / 'epochs.csv', EPOCH_FIELDS, self.epochs)
        if self._writer is not None:
            at = (entry['epoch'] + 1) * self.steps_per_epoch
            self._writer.add_scalar('loss/train_epoch', entry['train_loss'],
                                    at)
            if not math.isnan(entry['val_loss']):
                self._writer.add_scalar('loss/validation', entry['val_loss'],
                                        at)
            self._writer.flush()

    def close(self):
        r"""Closes the files and draws :obj:`history.png`."""
        from tg_nebp.plot import plot_training_history

        self._steps.close()
        if self._writer is not None:
            self._writer.close()
        plot_training_history(read_training_log(self.log_dir),
                              self.steps_per_epoch,
                              self.log_dir / 'history.png')

    def __enter__(self) -> 'TrainingLog':
        return self

    def __exit__(self, *exc):
        self.close()
