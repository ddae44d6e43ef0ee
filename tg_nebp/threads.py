r"""Intra-op threads that follow the load of the machine.

On a busy CPU, torch's OpenMP threads spin at the end of every parallel
region while waiting for a partner thread that another process has
displaced; the particle BP path runs many short regions per message-passing
call, so two threads on two busy cores can be several times slower than one
(see the README's *CPU under load*). A :class:`ThreadGovernor` keeps the
thread count at the cores that the other processes leave free.

Particle BP gives bit-identical results for any thread count (its test
runs the trackers at 1 and 2 threads), so governing its threads changes
only its speed. NEBP's learned layers do not (their matrix products round
by thread count): the command line governs the threads of BP runs only."""
import contextlib
import os
from typing import Callable, Iterator, Optional, Union

import torch

from tg_nebp.data.validation import check_positive_int

__all__ = ['ThreadGovernor', 'threads_in_force', 'runnable_elsewhere',
           'available_cores']


def available_cores() -> int:
    r"""The cores this process may run on (its CPU affinity)."""
    if hasattr(os, 'sched_getaffinity'):
        return len(os.sched_getaffinity(0))
    return os.cpu_count() or 1


def runnable_elsewhere() -> Optional[int]:
    r"""How many threads of other processes are runnable now: the running
    count of :obj:`/proc/loadavg` minus this process's runnable threads
    (:obj:`/proc/self/task/*/stat`); :obj:`None` where :obj:`/proc` is
    missing (not Linux)."""
    try:
        with open('/proc/loadavg') as f:
            running = int(f.read().split()[3].split('/')[0])
        mine = 0
        for task in os.listdir('/proc/self/task'):
            try:
                with open(f'/proc/self/task/{task}/stat') as f:
                    # the state follows the parenthesized command name
                    mine += f.read().rpartition(')')[2].split()[0] == 'R'
            except OSError:  # the thread ended meanwhile
                continue
    except (OSError, IndexError, ValueError):
        return None
    return max(running - mine, 0)


class ThreadGovernor:
    r"""Sets torch's intra-op thread count to the cores that other
    processes leave free, between :obj:`1` and :obj:`max_threads`:

    .. math::
        T = \min\left(T_\mathrm{max}, \max\left(1, C -
        \mathrm{round}(\bar{r})\right)\right),

    with :math:`C` the available cores and :math:`\bar{r}` a running mean
    of the threads of other processes that are runnable
    (:func:`runnable_elsewhere`), updated by every :meth:`update` call (the
    command line calls it after every time step). A new count takes effect
    once :obj:`patience` updates in a row ask for it, so that a passing
    process does not make the count flap; :meth:`close` (or leaving the
    :obj:`with` block) restores the count found at the start. Where the
    load cannot be read, the count is left alone.

    Args:
        max_threads (int, optional): The most threads to use.
            (default: :obj:`torch.get_num_threads()`)
        smoothing (float, optional): The weight of a new reading in the
            running mean. (default: :obj:`0.3`)
        patience (int, optional): Updates in a row that must ask for a
            new count before it is set. (default: :obj:`3`)
        read (callable, optional): Returns the runnable threads of other
            processes, or :obj:`None`. (default: :func:`runnable_elsewhere`)
        cores (int, optional): The available cores.
            (default: :func:`available_cores`)
    """

    def __init__(self, max_threads: Optional[int] = None,
                 smoothing: float = 0.3, patience: int = 3,
                 read: Callable[[], Optional[int]] = runnable_elsewhere,
                 cores: Optional[int] = None):
        if not 0 < smoothing <= 1:
            raise ValueError(f"'smoothing' must lie in (0, 1], got "
                             f"{smoothing}")
        if patience < 1:
            raise ValueError(f"'patience' must be positive, got {patience}")
        self.initial = torch.get_num_threads()
        # a count given is used or refused, never replaced
        self.max_threads = (self.initial if max_threads is None else
                            check_positive_int(max_threads, 'max_threads'))
        self.smoothing, self.patience, self.read = smoothing, patience, read
        self.cores = (available_cores() if cores is None else
                      check_positive_int(cores, 'cores'))
        self.mean: Optional[float] = None
        self.wanted, self.streak = None, 0
        self.threads = self.initial
        self.update(immediately=True)

    def target(self) -> int:
        r"""The thread count that the running mean asks for."""
        if self.mean is None:
            return self.threads
        free = self.cores - int(round(self.mean))
        return min(self.max_threads, max(1, free))

    def update(self, immediately: bool = False) -> int:
        r"""Takes a reading, sets the thread count if it is due to change
        (at once with :obj:`immediately`) and returns the count in force."""
        reading = self.read()
        if reading is None:
            return self.threads
        self.mean = (reading if self.mean is None else self.mean +
                     self.smoothing * (reading - self.mean))
        target = self.target()
        if target == self.threads:
            self.wanted, self.streak = None, 0
            return self.threads
        self.streak = self.streak + 1 if target == self.wanted else 1
        self.wanted = target
        if immediately or self.streak >= self.patience:
            torch.set_num_threads(target)
            self.threads, self.wanted, self.streak = target, None, 0
        return self.threads

    def close(self):
        r"""Restores the thread count found at the start."""
        if torch.get_num_threads() != self.initial:
            torch.set_num_threads(self.initial)
        self.threads = self.initial

    def __enter__(self) -> 'ThreadGovernor':
        return self

    def __exit__(self, *exc):
        self.close()


@contextlib.contextmanager
def threads_in_force(threads: Union[int, str, None] = None,
                     device: str = 'cpu'
                     ) -> Iterator[Optional[ThreadGovernor]]:
    r"""torch's CPU threads for the duration of the block: a count, or
    :obj:`"auto"`, a :class:`ThreadGovernor` (yielded, for the caller to
    :meth:`~ThreadGovernor.update` after every time step) on a CPU
    :obj:`device`; :obj:`None` leaves torch's count. The count found at
    the start is restored at the end."""
    if threads is not None and threads != 'auto':
        check_positive_int(threads, 'threads')
    initial = torch.get_num_threads()
    governor = None
    if threads == 'auto' and not str(device).startswith('cuda'):
        governor = ThreadGovernor()
    elif isinstance(threads, int):
        torch.set_num_threads(threads)
    try:
        yield governor
    finally:
        if torch.get_num_threads() != initial:
            torch.set_num_threads(initial)
