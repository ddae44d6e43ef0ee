r"""The one validation layer of :mod:`tg_nebp`.

Every public entry point (datasets, convolutions, trackers, CLI) calls these
checks, so bad input fails early with a :class:`ValueError` that names the
field and the offending index instead of producing NaNs far downstream.
"""
import math
import numbers
from typing import Optional, Sequence

import torch
from torch import Tensor
from torch_geometric import EdgeIndex

from tg_nebp.data.realization import num_steps_of, position_dim_of
from tg_nebp.utils import (compute_dtype, rounding_tolerance,
                           symmetric_psd_defects)

__all__ = [
    'check_lag',
    'check_graph',
    'check_position_dim',
    'check_link_features',
    'check_particles',
    'check_prior',
    'check_realization',
    'check_anchor',
    'magnitude_limit',
    'MAX_PRIOR_VARIANCE',
    'check_non_negative_int',
    'check_positive_int',
    'check_number',
    'check_links',
    'check_layer_inputs',
    'check_gaussian_belief',
    'check_edge_log_weights',
    'is_integer',
    'check_state_dim',
    'check_control',
]


def _first(mask: Tensor) -> int:
    return int(mask.nonzero()[0, 0])


#: The largest entry of a prior covariance accepted (square metres, and
#: the squared units of the other state entries): a standard deviation of
#: 10,000 km, beyond which a float64 filter's update of a range of about
#: a metre loses its digits (measured: every Gaussian tracker and the
#: bound finite up to 1e14, Gaussian BP singular at 1e150, the window's
#: and the IEKF's covariances indefinite at 1e18).
MAX_PRIOR_VARIANCE = 1e14


def magnitude_limit(dtype: torch.dtype) -> float:
    r"""The largest coordinate or range (in metres) accepted for a tensor of
    :obj:`dtype`: a quarter of the square root of the largest number of the
    dtype it is computed in (:func:`~tg_nebp.utils.compute_dtype`), so that
    squared distances between accepted positions and squared range
    residuals stay finite (float32: :math:`4.6 \cdot 10^{18}`)."""
    working = torch.promote_types(dtype, torch.float32)
    return math.sqrt(torch.finfo(working).max) / 4


def is_integer(value) -> bool:
    r"""Whether :obj:`value` is an integer (NumPy's too), not a bool."""
    return isinstance(value, numbers.Integral) and not isinstance(value, bool)


def check_positive_int(value, name: str) -> int:
    r"""Returns :obj:`value` as an :obj:`int` if it is an integer of at
    least one (a float such as :obj:`2.5` or a bool is a
    :class:`TypeError` naming :obj:`name`)."""
    if not is_integer(value):
        raise TypeError(f"'{name}' must be an integer, got {value!r}")
    if value < 1:
        raise ValueError(f"'{name}' must be positive, got {value}")
    return int(value)


def check_non_negative_int(value, name: str) -> int:
    r"""Returns :obj:`value` as an :obj:`int` if it is an integer of at
    least zero (a float, a string or a bool is a :class:`TypeError`
    naming :obj:`name`)."""
    if not is_integer(value):
        raise TypeError(f"'{name}' must be an integer, got {value!r}")
    if value < 0:
        raise ValueError(f"'{name}' must be at least 0, got {value}")
    return int(value)


def check_lag(lag) -> Optional[int]:
    r"""Returns a smoother's :obj:`lag` (the steps of its window, its own
    counted: a positive integer, :obj:`1` a filter) or :obj:`None` (every
    step of the sequence)."""
    return None if lag is None else check_positive_int(lag, 'lag')


def check_number(value, name: str, minimum: float = 0.0,
                 inclusive: bool = False,
                 maximum: float = math.inf) -> float:
    r"""Returns :obj:`value` as a :obj:`float` if it is a finite real number
    above :obj:`minimum` (or equal to it, if :obj:`inclusive`) and at most
    :obj:`maximum`; a string or a bool is a :class:`TypeError`, anything
    else out of range a :class:`ValueError`, both naming :obj:`name`."""
    if isinstance(value, bool) or not isinstance(value, numbers.Real):
        raise TypeError(f"'{name}' must be a number, got {value!r}")
    above = value >= minimum if inclusive else value > minimum
    if not (math.isfinite(value) and above):
        bound = 'at least' if inclusive else 'above'
        raise ValueError(f"'{name}' must be a finite number {bound} "
                         f"{minimum}, got {value}")
    if value > maximum:
        raise ValueError(f"'{name}' must be at most {maximum:g}, got "
                         f"{value}")
    return float(value)


def _too_large(values: Tensor) -> Tensor:
    return values.abs() > magnitude_limit(values.dtype)


def check_graph(edge_index: Tensor, num_nodes: int,
                name: str = 'edge_index') -> None:
    r"""Checks that :obj:`edge_index` is a :obj:`[2, E]` integer tensor with
    node indices in :obj:`[0, num_nodes)` and no self-loops."""
    if num_nodes <= 0:
        raise ValueError(f"'num_nodes' must be positive, got {num_nodes} "
                         f"(empty graph)")
    if not isinstance(edge_index, Tensor) or edge_index.dim() != 2 \
            or edge_index.size(0) != 2:
        shape = tuple(edge_index.shape) if isinstance(edge_index,
                                                      Tensor) else None
        raise ValueError(f"'{name}' must have shape [2, E], got {shape}")
    if edge_index.dtype not in (torch.long, torch.int32):
        raise ValueError(f"'{name}' must be an integer tensor, got "
                         f"{edge_index.dtype}")
    if edge_index.numel() == 0:
        return
    bad = (edge_index < 0) | (edge_index >= num_nodes)
    if bool(bad.any()):
        row, e = bad.nonzero()[0].tolist()
        raise ValueError(f"'{name}[{row}, {e}]' = {int(edge_index[row, e])} "
                         f"is out of range for {num_nodes} nodes")
    loop = edge_index[0] == edge_index[1]
    if bool(loop.any()):
        e = _first(loop)
        raise ValueError(f"'{name}[:, {e}]' is a self-loop on node "
                         f"{int(edge_index[0, e])}")
    if isinstance(edge_index, EdgeIndex):
        _check_edge_index_claims(edge_index, num_nodes, name)


def _check_edge_index_claims(edge_index: EdgeIndex, num_nodes: int,
                             name: str) -> None:
    # the convs trust an EdgeIndex's sort order (they sum receiver
    # segments) and size their output by its sparse size: a false claim
    # would give wrong numbers, not an error
    size = edge_index.sparse_size()
    if any(s is not None and s != num_nodes for s in size):
        raise ValueError(f"'{name}' has sparse size {tuple(size)} but the "
                         f"graph has {num_nodes} nodes")
    for row, order in ((0, 'row'), (1, 'col')):
        if getattr(edge_index, f'is_sorted_by_{order}'):
            down = edge_index.as_tensor()[row].diff() < 0
            if bool(down.any()):
                e = _first(down) + 1
                raise ValueError(f"'{name}' claims sort_order='{order}' but "
                                 f"'{name}[{row}, {e}]' = "
                                 f"{int(edge_index[row, e])} follows "
                                 f"{int(edge_index[row, e - 1])}")


def check_link_features(edge_attr: Tensor, num_edges: int,
                        features: Sequence[str] = ('range', ),
                        name: str = 'edge_attr',
                        negative_ranges: bool = False) -> None:
    r"""Checks the link features :obj:`[E, F]`: at least the
    :obj:`features` that a measurement model reads (the leading columns,
    the range first), floating point and finite; the range small enough
    for squared distances, and non-negative unless the model's likelihood
    takes :obj:`negative_ranges` (the measurement role's
    :attr:`~tg_nebp.models.MeasurementModel.negative_ranges`)."""
    if not isinstance(edge_attr, Tensor) or edge_attr.dim() != 2 \
            or edge_attr.size(0) != num_edges \
            or edge_attr.size(1) < len(features):
        shape = (tuple(edge_attr.shape) if isinstance(edge_attr, Tensor)
                 else None)
        raise ValueError(f"'{name}' must have shape [{num_edges}, F] with "
                         f"the link features {tuple(features)} first, got "
                         f"{shape}")
    if not edge_attr.is_floating_point():
        raise ValueError(f"'{name}' must be a floating point tensor, got "
                         f"{edge_attr.dtype}")
    bad = ~torch.isfinite(edge_attr)
    if bool(bad.any()):
        e, f = bad.nonzero()[0].tolist()
        index = f'{e}' if edge_attr.size(1) == 1 else f'{e}, {f}'
        raise ValueError(f"'{name}[{index}]' = {float(edge_attr[e, f])} is "
                         f"not finite")
    ranges = edge_attr[:, 0]
    neg = ranges < 0
    if not negative_ranges and bool(neg.any()):
        e = _first(neg)
        raise ValueError(f"'{name}[{e}]' = {float(ranges[e])} is a "
                         f"negative range")
    big = _too_large(ranges.abs())
    if bool(big.any()):
        e = _first(big)
        raise ValueError(f"'{name}[{e}]' = {float(ranges[e]):.3g} is too "
                         f"large a range (at most "
                         f"{magnitude_limit(ranges.dtype):.3g}: its square "
                         f"must be finite in {compute_dtype(ranges)})")


def check_particles(particles: Tensor, log_weights: Tensor,
                    num_nodes: Optional[int] = None,
                    state_dim: Optional[int] = None,
                    weights_name: str = 'log_weights') -> None:
    r"""Checks that :obj:`particles` :obj:`[N, K, D]` and :obj:`log_weights`
    :obj:`[N, K]` agree with each other and with the model, and that the
    particles are finite and no log-weight is NaN or :math:`+\infty`."""
    if not isinstance(particles, Tensor) or particles.dim() != 3:
        raise ValueError(f"'particles' must have shape [N, K, D], got "
                         f"{tuple(getattr(particles, 'shape', ()))}")
    if num_nodes is not None and particles.size(0) != num_nodes:
        raise ValueError(f"'particles' holds {particles.size(0)} nodes but "
                         f"the graph has {num_nodes}")
    if state_dim is not None and particles.size(2) != state_dim:
        raise ValueError(f"'particles' has state size {particles.size(2)} "
                         f"but the model expects {state_dim}")
    if particles.size(2) < 2 or particles.size(2) % 2:
        raise ValueError(f"'particles' must hold a position, then a "
                         f"velocity, of the same dimension, got state size "
                         f"{particles.size(2)}")
    if particles.size(1) == 0:
        raise ValueError("'particles' holds K = 0 particles per node")
    if not isinstance(log_weights, Tensor) \
            or log_weights.shape != particles.shape[:2]:
        raise ValueError(f"'{weights_name}' must have shape "
                         f"{list(particles.shape[:2])} to match 'particles' "
                         f"(K = {particles.size(1)}), got "
                         f"{list(getattr(log_weights, 'shape', []))}")
    if not (particles.is_floating_point()
            and log_weights.is_floating_point()):
        raise TypeError(f"'particles' and '{weights_name}' must be floating "
                        f"point tensors, got {particles.dtype} and "
                        f"{log_weights.dtype}")
    bad = ~torch.isfinite(particles).all(dim=-1).all(dim=-1)
    if bool(bad.any()):
        raise ValueError(f"'particles[{_first(bad)}]' holds a non-finite "
                         f"value")
    big = _too_large(particles).flatten(1).any(-1)
    if bool(big.any()):
        raise ValueError(f"'particles[{_first(big)}]' holds a value beyond "
                         f"{magnitude_limit(particles.dtype):.3g}, too large "
                         f"for {compute_dtype(particles)} distances and "
                         f"covariances")
    bad = (torch.isnan(log_weights) | (log_weights == float('inf'))).any(-1)
    if bool(bad.any()):
        raise ValueError(f"'{weights_name}[{_first(bad)}]' holds NaN or "
                         f"+inf")
    # -inf is a zero weight; finite values must leave room for the sums of
    # messages
    big = (_too_large(log_weights) & torch.isfinite(log_weights)).any(-1)
    if bool(big.any()):
        raise ValueError(f"'{weights_name}[{_first(big)}]' holds a finite "
                         f"value beyond "
                         f"{magnitude_limit(log_weights.dtype):.3g} in "
                         f"magnitude")
    zero = torch.isneginf(log_weights).all(-1)
    if bool(zero.any()):
        raise ValueError(f"'{weights_name}[{_first(zero)}]' is -inf for "
                         f"every particle: zero weights are no belief")


def check_anchor(anchor: Tensor, num_nodes: int) -> None:
    r"""Checks that :obj:`anchor` is a bool mask of shape :obj:`[N]`."""
    if not isinstance(anchor, Tensor) or anchor.dtype != torch.bool \
            or anchor.shape != (num_nodes, ):
        raise ValueError(f"'anchor' must be a bool tensor of shape "
                         f"[{num_nodes}], got "
                         f"{getattr(anchor, 'dtype', type(anchor))} "
                         f"{list(getattr(anchor, 'shape', []))}")


def check_prior(prior_mean: Tensor, prior_cov: Tensor, anchor: Tensor,
                atol: float = 1e-6,
                position_dim: Optional[int] = None) -> None:
    r"""Checks the prior: finite means (an anchor's mean is its known
    position; the first :obj:`position_dim` entries are the position, the
    first half of a state by default), symmetric positive semi-definite
    covariances whose entries are at most
    :data:`~tg_nebp.data.validation.MAX_PRIOR_VARIANCE`."""
    n, d = prior_mean.shape
    if not prior_cov.is_floating_point():
        raise ValueError(f"'prior_cov' must be a floating point tensor, got "
                         f"{prior_cov.dtype}")
    if prior_cov.shape != (n, d, d):
        raise ValueError(f"'prior_cov' must have shape [{n}, {d}, {d}], got "
                         f"{list(prior_cov.shape)}")
    bad = ~torch.isfinite(prior_mean).all(-1)
    if bool(bad.any()):
        i = _first(bad)
        what = ('anchor without a known position' if bool(anchor[i]) else
                'non-finite prior mean')
        raise ValueError(f"'prior_mean[{i}]': {what}")
    if position_dim is None:
        position_dim = d // 2
    big = _too_large(prior_mean[:, :position_dim]).any(-1)
    if bool(big.any()):
        raise ValueError(f"'prior_mean[{_first(big)}]' holds a position "
                         f"beyond {magnitude_limit(prior_mean.dtype):.3g}, "
                         f"too large for {compute_dtype(prior_mean)} "
                         f"distances")
    bad = ~torch.isfinite(prior_cov).flatten(1).all(-1)
    if bool(bad.any()):
        raise ValueError(f"'prior_cov[{_first(bad)}]' is not finite")
    # a variance near the dtype's largest number overflows the first
    # symmetrization, and one of 1e18 m^2 loses every digit of a unit
    # range's update in a covariance-form (float64) filter
    huge = (prior_cov.abs() > MAX_PRIOR_VARIANCE).flatten(1).any(-1)
    if bool(huge.any()):
        raise ValueError(f"'prior_cov[{_first(huge)}]' holds an entry beyond "
                         f"{MAX_PRIOR_VARIANCE:.0e} (a standard deviation of "
                         f"10,000 km): give a finite, smaller prior")
    _check_symmetric_psd(prior_cov, 'prior_cov', atol)


def _check_symmetric_psd(matrices: Tensor, name: str, atol: float) -> None:
    # symmetric and positive semi-definite up to 'atol' relative to the
    # largest entry, or the rounding of the dtype where that is coarser:
    # covariances and information matrices
    asymmetric, indefinite, lowest = symmetric_psd_defects(
        matrices, max(atol, rounding_tolerance(matrices.dtype)))
    if bool(asymmetric.any()):
        raise ValueError(f"'{name}[{_first(asymmetric)}]' is not symmetric")
    if bool(indefinite.any()):
        i = _first(indefinite)
        raise ValueError(f"'{name}[{i}]' is not positive semi-definite "
                         f"(smallest eigenvalue {float(lowest[i]):.3g})")


def check_state_dim(size: int, motion,
                    position_dim: Optional[int] = None) -> None:
    r"""A :class:`ValueError` if states of size :obj:`size` are not what the
    motion model :obj:`motion` is for (a model that states its
    :attr:`~tg_nebp.models.MotionModel.state_dim`), or, with
    :obj:`position_dim` (a realization's,
    :func:`~tg_nebp.data.position_dim_of`), if the model's
    layout puts another number of position entries first; and if the
    layout (:meth:`~tg_nebp.models.MotionModel.layout`) is not one of a
    state of that size (an angle index outside it). The model is
    read by its role's attributes only: the models import this module,
    which imports none of them."""
    if motion.state_dim is not None and size != motion.state_dim:
        raise ValueError(f"'prior_mean' holds states of size {size} but the "
                         f"motion model {motion} has state dimension "
                         f"{motion.state_dim}")
    layout = motion.layout(size)
    if layout.size != size or not 0 < layout.position_dim <= size:
        raise ValueError(f"the motion model {motion} lays out a state of "
                         f"size {size} as {layout.size} entries with "
                         f"{layout.position_dim} of position")
    for index in layout.angles:
        if isinstance(index, bool) or not isinstance(index, int) or \
                not 0 <= index < size:
            raise ValueError(f"the motion model {motion} names angle index "
                             f"{index!r} of a state of size {size} (its "
                             f"entries are 0 to {size - 1})")
    if position_dim is not None and layout.position_dim != position_dim:
        raise ValueError(f"the realization's positions have "
                         f"{position_dim} entries but the motion model "
                         f"{motion} reads {layout.position_dim}"
                         f" of a state of size {size}")


def check_control(data, motion) -> None:
    r"""Checks a realization's known inputs against its motion model
    :obj:`motion` (its :attr:`~tg_nebp.models.MotionModel.control_dim`):
    none for a model that takes none; else :obj:`control` :math:`(N, T,
    C)`, floating point, :math:`C` the model's
    :attr:`~tg_nebp.models.MotionModel.control_dim`, finite or NaN (a NaN
    row: no input for that agent and step). A realization without
    :obj:`control` is fine for any model (every step without input)."""
    control = getattr(data, 'control', None)
    if control is None:
        return
    if motion.control_dim == 0:
        raise ValueError(f"the realization carries known inputs "
                         f"('control') but the motion model {motion} takes "
                         f"none")
    n, steps = data.num_nodes, num_steps_of(data)
    shape = (n, steps, motion.control_dim)
    if not (isinstance(control, Tensor) and tuple(control.shape) == shape):
        raise ValueError(f"'control' must have shape {list(shape)} (the "
                         f"motion model {motion} takes inputs of "
                         f"{motion.control_dim}), got "
                         f"{list(getattr(control, 'shape', []))}")
    if not control.is_floating_point():
        raise ValueError(f"'control' must be a floating point tensor, got "
                         f"{control.dtype}")
    bad = torch.isinf(control).flatten(1).any(-1)
    if bool(bad.any()):
        i = _first(bad)
        t = int(torch.isinf(control[i]).any(-1).nonzero()[0, 0])
        raise ValueError(f"'control[{i}, {t}]' holds an infinite value (a "
                         f"step without input is a row of NaN)")
    beyond = ~motion.representable(control)
    if bool(beyond.any()):
        i, t = beyond.nonzero()[0].tolist()
        raise ValueError(f"'control[{i}, {t}]' = {control[i, t].tolist()} "
                         f"is beyond the inputs the motion model {motion} "
                         f"represents ({motion.input_limit})")
    partial = torch.isnan(control).any(-1) & ~torch.isnan(control).all(-1)
    if bool(partial.any()):
        i, t = partial.nonzero()[0].tolist()
        raise ValueError(f"'control[{i}, {t}]' is partly NaN: an input is "
                         f"given whole or not at all (a row of NaN)")


def check_position_dim(position_dim: int, state_size: Optional[int] = None,
                       what: str = 'the tracker') -> int:
    r"""The positions' dimension :obj:`position_dim` (2 or 3), and, with
    :obj:`state_size`, a :class:`ValueError` naming both if states of that
    size are not :obj:`what` was built for (:math:`2D`)."""
    if isinstance(position_dim, bool) or position_dim not in (2, 3):
        raise ValueError(f"'position_dim' must be 2 or 3, got "
                         f"{position_dim!r}")
    if state_size is not None and state_size != 2 * position_dim:
        raise ValueError(f"{what} was built for {position_dim}-D positions "
                         f"(states of size {2 * position_dim}), but the "
                         f"realization holds states of size {state_size}")
    return position_dim


def check_realization(data, features: Sequence[str] = ('range', ),
                      negative_ranges: bool = False) -> None:
    r"""Checks a (possibly batched) :class:`~tg_nebp.data.Realization`
    whose :obj:`edge_attr` holds (at least) the link :obj:`features`
    (negative ranges where :obj:`negative_ranges`)."""
    for key in ('edge_index', 'edge_attr', 'edge_time', 'anchor',
                'prior_mean', 'prior_cov', 'num_steps'):
        if getattr(data, key, None) is None:
            raise ValueError(f"realization is missing the field '{key}'")
    n = data.num_nodes
    if n is None or n <= 0:
        raise ValueError(f"'num_nodes' must be positive, got {n} "
                         f"(empty graph)")
    anchor = data.anchor
    check_anchor(anchor, n)
    if bool(anchor.all()):
        raise ValueError("'anchor': the graph has no agent to localize")
    check_graph(data.edge_index, n)
    check_link_features(data.edge_attr, data.edge_index.size(1), features,
                        negative_ranges=negative_ranges)
    into_anchor = anchor[data.edge_index[1]]
    if bool(into_anchor.any()):
        e = _first(into_anchor)
        raise ValueError(f"'edge_index[:, {e}]' ends at anchor "
                         f"{int(data.edge_index[1, e])}: anchors never "
                         f"receive measurements")
    t = data.edge_time
    if t.shape != (data.edge_index.size(1), ):
        raise ValueError(f"'edge_time' must have shape "
                         f"[{data.edge_index.size(1)}], got {list(t.shape)}")
    if t.is_floating_point() or t.is_complex() or t.dtype == torch.bool:
        raise ValueError(f"'edge_time' must be an integer tensor, got "
                         f"{t.dtype}")
    steps = num_steps_of(data)
    if steps < 1:
        raise ValueError(f"'num_steps' must be at least 1, got {steps}")
    bad = (t < 0) | (t >= steps)
    if bool(bad.any()):
        e = _first(bad)
        raise ValueError(f"'edge_time[{e}]' = {int(t[e])} is outside "
                         f"[0, {steps})")
    mean = data.prior_mean
    declared = getattr(data, 'position_dim', None)
    if declared is None:
        if not (isinstance(mean, Tensor) and mean.dim() == 2
                and mean.size(0) == n and mean.size(1) in (4, 6)):
            raise ValueError(f"'prior_mean' must have shape [{n}, 4] or "
                             f"[{n}, 6] (a 2-D or 3-D position, then the "
                             f"velocity; another layout declares its "
                             f"'position_dim'), got "
                             f"{list(getattr(mean, 'shape', []))}")
        position_dim = mean.size(1) // 2
    else:
        position_dim = position_dim_of(data)
        if position_dim not in (2, 3):
            raise ValueError(f"'position_dim' must be 2 or 3, got "
                             f"{position_dim}")
        if not (isinstance(mean, Tensor) and mean.dim() == 2
                and mean.size(0) == n and mean.size(1) >= position_dim):
            raise ValueError(f"'prior_mean' must have shape [{n}, S] with "
                             f"S >= {position_dim} (the position first), "
                             f"got {list(getattr(mean, 'shape', []))}")
    if not data.prior_mean.is_floating_point():
        raise ValueError(f"'prior_mean' must be a floating point tensor, got "
                         f"{data.prior_mean.dtype}")
    check_prior(data.prior_mean, data.prior_cov, anchor,
                position_dim=position_dim)
    states = getattr(data, 'states', None)
    if states is not None and (states.dim() != 3 or states.size(0) != n
                               or states.size(1) != steps
                               or states.size(2) != data.prior_mean.size(1)):
        raise ValueError(f"'states' must have shape [{n}, {steps}, "
                         f"{data.prior_mean.size(1)}], got "
                         f"{list(states.shape)}")
    if states is not None:
        # an agent without ground truth: its whole row NaN (tracked, not
        # scored); anything else not finite is damage
        unknown = torch.isnan(states).flatten(1).all(-1) & ~anchor
        bad = ~torch.isfinite(states).flatten(1).all(-1) & ~unknown
        if bool(bad.any()):
            raise ValueError(f"'states[{_first(bad)}]' holds a non-finite "
                             f"value (a node without ground truth: an "
                             f"agent whose every state is NaN)")


def check_links(edge_index: Tensor, edge_attr: Tensor,
                features: Sequence[str], num_nodes: int,
                anchor: Optional[Tensor] = None,
                negative_ranges: bool = False) -> None:
    r"""The checks of one message passing step's links, shared by every
    convolution: the graph (:func:`check_graph`: indices in range, no
    self-loop), the link :obj:`features` that the measurement model reads
    (:func:`check_link_features`: finite ranges, non-negative unless
    :obj:`negative_ranges`) and the anchor mask (:func:`check_anchor`)."""
    check_graph(edge_index, num_nodes)
    check_link_features(edge_attr, edge_index.size(1), features,
                        negative_ranges=negative_ranges)
    if anchor is not None:
        check_anchor(anchor, num_nodes)


def check_layer_inputs(particles: Tensor, log_weights: Tensor,
                       edge_index: Tensor, edge_attr: Tensor,
                       features: Sequence[str],
                       anchor: Optional[Tensor] = None,
                       sender_log_weights: Optional[Tensor] = None,
                       state_dim: Optional[int] = None,
                       negative_ranges: bool = False) -> None:
    r"""The checks of one particle message passing step's inputs, shared by
    the particle convolutions and the trackers' :meth:`update`: particles
    and (sender) log-weights, and the links (:func:`check_links`;
    :obj:`negative_ranges` as there)."""
    num_nodes = particles.size(0) if isinstance(particles, Tensor) else None
    check_particles(particles, log_weights, state_dim=state_dim)
    if sender_log_weights is not None:
        check_particles(particles, sender_log_weights,
                        weights_name='sender_log_weights')
    check_links(edge_index, edge_attr, features, num_nodes, anchor,
                negative_ranges)


def check_gaussian_belief(mean: Tensor, info: Tensor, name: str,
                          num_nodes: Optional[int] = None,
                          atol: float = 1e-6) -> None:
    r"""Checks Gaussian beliefs in information form (:obj:`name` names
    them in errors, e.g. :obj:`"belief"`): means :obj:`[N, S]` and
    information :obj:`[N, S, S]`, floating point, finite, symmetric and
    positive semi-definite (an anchor's zero information included)."""
    for field, value, dim in (('mean', mean, 2), ('info', info, 3)):
        if not (isinstance(value, Tensor) and value.dim() == dim
                and value.is_floating_point()):
            raise ValueError(f"'{name}.{field}' must be a floating point "
                             f"tensor of {dim} dimensions, got "
                             f"{getattr(value, 'dtype', type(value))} "
                             f"{list(getattr(value, 'shape', []))}")
    n, size = mean.shape
    if num_nodes is not None and n != num_nodes:
        raise ValueError(f"'{name}.mean' holds {n} nodes but the graph has "
                         f"{num_nodes}")
    if info.shape != (n, size, size):
        raise ValueError(f"'{name}.info' must have shape [{n}, {size}, "
                         f"{size}], got {list(info.shape)}")
    for field, value in (('mean', mean), ('info', info)):
        bad = ~torch.isfinite(value).reshape(n, -1).all(-1)
        if bool(bad.any()):
            raise ValueError(f"'{name}.{field}[{_first(bad)}]' holds a "
                             f"non-finite value")
    big = _too_large(mean).any(-1)
    if bool(big.any()):
        raise ValueError(f"'{name}.mean[{_first(big)}]' holds a value "
                         f"beyond {magnitude_limit(mean.dtype):.3g}")
    _check_symmetric_psd(info, f'{name}.info', atol)


def check_edge_log_weights(weights: Tensor, num_edges: int,
                           num_particles: int,
                           name: str = 'edge_sender_log_weights') -> None:
    r"""Checks per-edge log-weights :obj:`[E, K]` (the senders' extrinsic
    beliefs of :class:`~tg_nebp.nn.conv.ParticleBPConv`): their shape, and
    no NaN or :math:`+\infty`."""
    if not isinstance(weights, Tensor) or weights.shape != (num_edges,
                                                           num_particles):
        raise ValueError(f"'{name}' must have shape [{num_edges}, "
                         f"{num_particles}], got "
                         f"{list(getattr(weights, 'shape', []))}")
    bad = (torch.isnan(weights) | (weights == float('inf'))).any(-1)
    if bool(bad.any()):
        raise ValueError(f"'{name}[{_first(bad)}]' holds NaN or +inf")
