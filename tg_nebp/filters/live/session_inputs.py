r"""What a live session (:class:`~tg_nebp.filters.TrackingSession`) is
given, checked before it changes anything: the nodes that join
(:class:`AgentPrior`, :class:`AnchorAt`), the user's identifiers, lists of
numbers and times in seconds; and the rows of a tracker's message put back
into the user's identifiers."""
import math
import numbers
import re
from typing import List, NamedTuple, Optional, Sequence, Tuple, Union

import torch
from torch import Tensor

__all__ = ['AgentPrior', 'AnchorAt']

# the longest time step or time accepted, in seconds (a thousand years):
# beyond it the motion model's noise overflows
LONGEST_SECONDS = 3e10

Identifier = Union[str, int]
class AgentPrior(NamedTuple):
    r"""A joining agent: the prior :obj:`mean` :math:`(S)` and :obj:`cov`
    :math:`(S, S)` of its state :math:`[\mathbf{p}, \mathbf{v}]` (a state
    before the step it joins at, predicted like the prior of a
    realization's first step)."""
    mean: Sequence[float]
    cov: Sequence[Sequence[float]]


class AnchorAt(NamedTuple):
    r"""A joining anchor at the known :obj:`position` :math:`(D)`."""
    position: Sequence[float]


def checked_identifier(value, where: str) -> Identifier:
    # a user's identifier: a string or an integer (not a bool, whose JSON
    # form is not an identifier)
    if isinstance(value, str) or (isinstance(value, numbers.Integral)
                                  and not isinstance(value, bool)):
        return value if isinstance(value, str) else int(value)
    raise ValueError(f"{where}: an identifier is a string or an integer, "
                     f"got {value!r}")


def holds_truth_values(value) -> bool:
    # whether a value (nested lists, an array, a tensor) holds a bool
    if isinstance(value, bool):
        return True
    if isinstance(value, (list, tuple)):
        return any(holds_truth_values(item) for item in value)
    return str(getattr(value, 'dtype', '')) in ('bool', 'torch.bool')


def checked_numbers(value, shape: Tuple[Optional[int], ...],
             where: str) -> Tensor:
    # numbers (a list, an array, a tensor) of the given shape (None: any
    # size), in float64; true and false are not numbers here (as a time
    # step's are not)
    if holds_truth_values(value):
        raise ValueError(f"{where} must be numbers, not true or false: got "
                         f"{value!r}"[:200])
    try:
        tensor = torch.as_tensor(value, dtype=torch.float64).cpu()
    except OverflowError:  # an integer beyond any float
        raise ValueError(f"{where} holds a number too large for a float: "
                         f"{value!r}"[:200]) from None
    except (TypeError, ValueError, RuntimeError):
        raise ValueError(f"{where} must be a list of numbers of shape "
                         f"{list(shape)}, got {value!r}") from None
    if tensor.dim() != len(shape) or any(
            n is not None and n != m for n, m in zip(shape, tensor.shape)):
        raise ValueError(f"{where} must have shape {list(shape)}, got "
                         f"{list(tensor.shape)}")
    return tensor


def seconds_or_none(value) -> Optional[float]:
    # a time or time step as a float: None for anything but a finite real
    # number within the longest accepted (an integer beyond any float
    # included)
    if isinstance(value, bool) or not isinstance(value, numbers.Real):
        return None
    try:
        value = float(value)
    except OverflowError:
        return None
    return value if math.isfinite(value) and abs(value) <= LONGEST_SECONDS \
        else None


def identified(message: str, ids: List[Identifier]) -> str:
    # a tracker's error names nodes by their rows ('node 7'): the
    # identifiers of those rows added
    rows = sorted({int(row) for row in re.findall(r'\bnode (\d+)', message)
                   if int(row) < len(ids)})
    if not rows:
        return message
    return message + ' (' + ', '.join(f'node {row} is {ids[row]!r}'
                                      for row in rows) + ')'
