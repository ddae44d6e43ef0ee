r"""What a tracker's state may hold, field by field, and the check of a
state against it: what a :class:`~tg_nebp.filters.TrackingSession` runs on
a saved state before it replaces anything, so that a damaged file (a NaN
covariance, a mean of the wrong width, anchor flags of 0.5, a weight that
is not normalized) is refused by the field's name instead of tracked."""
import math
from typing import Dict, NamedTuple, Optional, Sequence, Tuple

import torch
from torch import Tensor

from tg_nebp.utils import rounding_tolerance, symmetric_psd_defects

__all__ = ['StateField', 'FIELD_KINDS', 'check_state']

#: Every kind of a state's field, :obj:`"float"` (finite),
#: :obj:`"cov"` (finite, symmetric positive semi-definite in its last two
#: dimensions, to the rounding of its dtype:
#: :func:`~tg_nebp.utils.rounding_tolerance`), :obj:`"nan"` (finite or
#: NaN: NaN marks an entry that is not there), :obj:`"log_weights"`
#: (normalized log-weights along the last
#: dimension: no NaN, no :math:`+\infty`), :obj:`"bool"` and
#: :obj:`"index"` (integers, at least zero).
FIELD_KINDS = ('float', 'cov', 'nan', 'log_weights', 'bool', 'index')

class StateField(NamedTuple):
    r"""One field of a tracker's state: its :obj:`shape`, a name per
    dimension (:obj:`"N"` the nodes, :obj:`"S"` the state entries, another
    name a size that every field naming it shares, :obj:`"*"` any size,
    a trailing :obj:`"..."` any further dimensions), its :obj:`kind` (one
    of :obj:`FIELD_KINDS`), whether :obj:`None` is allowed
    (:obj:`optional`) and whether it is a tuple of such tensors
    (:obj:`tuple`: each element checked)."""
    shape: Tuple[str, ...]
    kind: str = 'float'
    optional: bool = False
    tuple: bool = False


def _shape_error(name: str, value: Tensor, shape: Sequence[str],
                 sizes: Dict[str, int], like: Optional[Tensor],
                 bound_by: Dict[str, str]) -> Optional[str]:
    # what is wrong with the shape of 'value' against 'shape', binding the
    # named sizes on their first use (the dimensions of a trailing '...'
    # those of 'like', where given); None if nothing
    fixed = list(shape)
    rest = bool(fixed) and fixed[-1] == '...'
    if rest:
        fixed = fixed[:-1]
    if value.dim() < len(fixed) or (not rest and value.dim() != len(fixed)):
        return (f"{name} has shape {list(value.shape)}, expected "
                f"({', '.join(shape)})")
    if rest and like is not None and \
            value.shape[len(fixed):] != like.shape[len(fixed):]:
        return (f"{name} has shape {list(value.shape)}, expected "
                f"{list(like.shape[len(fixed):])} after its first "
                f"{len(fixed)}")
    for k, symbol in enumerate(fixed):
        size = value.size(k)
        if symbol == '*':
            continue
        if symbol.isdigit():
            expected = int(symbol)
        else:
            expected = sizes.setdefault(symbol, size)
            bound_by.setdefault(symbol, name)
        if size != expected:
            return (f"{name} has {size} entries in dimension {k}, expected "
                    f"{expected} ({symbol}: "
                    f"{bound_by.get(symbol, 'the number of ' + symbol)})")
    return None


def _value_error(name: str, value: Tensor, kind: str) -> Optional[str]:
    # what is wrong with the values of 'value' for its kind; None if
    # nothing
    if kind == 'bool':
        return None if value.dtype == torch.bool else \
            f"{name} must be booleans, got {value.dtype}"
    if kind == 'index':
        if value.dtype != torch.long:
            return f"{name} must be int64 indices, got {value.dtype}"
        if value.numel() and int(value.min()) < 0:
            return f"{name} holds a negative index"
        return None
    if not value.is_floating_point():
        return f"{name} must be floating point, got {value.dtype}"
    if kind == 'nan':
        bad = value.isinf()
    elif kind == 'log_weights':
        bad = value.isnan() | (value == math.inf)
    else:
        bad = ~value.isfinite()
    if bool(bad.any()):
        at = [int(i) for i in bad.nonzero()[0]]
        return f"{name} holds a non-finite value at {at}"
    if kind == 'log_weights' and value.numel():
        total = torch.logsumexp(value.double(), -1)
        if float(total.abs().max()) > 1e-4:
            return (f"{name} are not normalized (their exponentials sum to "
                    f"{float(total.exp().flatten()[total.abs().argmax()])})")
    if kind == 'cov' and (value.dim() < 2 or value.size(-1) != value.size(-2)):
        return f"{name} holds covariances that are not square"
    if kind == 'cov' and value.numel():
        asymmetric, indefinite, lowest = symmetric_psd_defects(
            value.reshape(-1, value.size(-2), value.size(-1)))
        if bool(asymmetric.any()):
            return (f"{name} holds a covariance that is not symmetric "
                    f"(beyond {rounding_tolerance(value.dtype):.1e} of its "
                    f"largest entry)")
        if bool(indefinite.any()):
            return (f"{name} holds a covariance that is not positive "
                    f"semi-definite (eigenvalue "
                    f"{float(lowest[indefinite].min()):.3g})")
    return None


def check_state(state, fields: Dict[str, StateField], num_nodes: int,
                state_size: int, template=None) -> Dict[str, int]:
    r"""Raises a :class:`ValueError` naming the field (and element) of
    :obj:`state` (a :class:`~typing.NamedTuple`) that does not fit its
    :obj:`fields`: a :obj:`None` where a tensor belongs, a shape off
    :obj:`num_nodes` nodes, :obj:`state_size` entries or a size another
    field gives, a value that its :obj:`kind` refuses, and against a
    :obj:`template` (a state of the same type made afresh, of any number
    of nodes): a float dtype other than the template's field's (where it
    has one; else than the state's first float dtype), dimensions of a
    trailing :obj:`"..."` other than the template's. Returns the sizes
    that the names bound."""
    sizes = {'N': num_nodes, 'S': state_size}
    bound_by = {'N': 'the nodes', 'S': 'the state entries'}
    expected = None
    for name, field in fields.items():
        value = getattr(state, name)
        like = None if template is None else getattr(template, name)
        likes = like if field.tuple and like is not None else (like, )
        label = f"the state's '{name}'"
        if value is None:
            if field.optional:
                continue
            raise ValueError(f"{label} is missing")
        items = value if field.tuple else (value, )
        if field.tuple and not isinstance(value, (tuple, list)):
            raise ValueError(f"{label} must be a tuple of tensors")
        for k, item in enumerate(items):
            where = f"{label}[{k}]" if field.tuple else label
            if not isinstance(item, Tensor):
                raise ValueError(f"{where} must be a tensor, got "
                                 f"{type(item).__name__}")
            same = likes[k] if k < len(likes) else None
            problem = (_shape_error(where, item, field.shape, sizes, same,
                                    bound_by) or
                       _value_error(where, item, field.kind))
            if problem:
                raise ValueError(problem)
            if item.is_floating_point():
                dtype = same.dtype if same is not None else expected
                if dtype is not None and item.dtype != dtype:
                    raise ValueError(f"{where} is {item.dtype}, expected "
                                     f"{dtype}")
                expected = expected or item.dtype
    return sizes
