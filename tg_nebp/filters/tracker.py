r"""What every tracker shares: the estimates it yields per time step and
for a whole sequence, the checks of a realization against its models, and
the fields it reports in :obj:`metrics.json`. A new inference method is a
:class:`Tracker` whose :meth:`~Tracker.steps` yields :class:`StepOutput`:
every metric, figure, :func:`~tg_nebp.evaluation.track_dataset`, the
compare table and the CLI then work with it unchanged. With
:meth:`~Tracker.initial_state`, :meth:`~Tracker.step` and its
:attr:`~Tracker.state_type` it also runs live
(:class:`~tg_nebp.filters.TrackingSession`, :obj:`tg-nebp track`)."""
from typing import Any, Dict, Iterator, NamedTuple, Optional

import torch
from torch import Tensor

from tg_nebp.data.realization import (Realization, controls_of,
                                      position_dim_of)
from tg_nebp.data.validation import (check_control, check_realization,
                                     check_state_dim)
from tg_nebp.filters.state import check_state
from tg_nebp.models import MeasurementModel, MotionModel, resolve_models

__all__ = ['Tracker', 'StepOutput', 'TrackOutput', 'Smoothed',
           'with_control']


def with_control(method, settings: Dict[str, Any]) -> Dict[str, Any]:
    r""":obj:`settings` of a tracker or bound :obj:`method` with
    :obj:`"control": false` added where it ignores known inputs
    (:attr:`Tracker.use_control`)."""
    return settings if method.use_control else dict(settings, control=False)


class StepOutput(NamedTuple):
    r"""What a tracker yields at time index :obj:`t`: the estimate
    :obj:`mean` :math:`(N, S)`, its covariance :obj:`cov` :math:`(N, S,
    S)` and, for the particle trackers, the particle belief
    (:obj:`particles` :math:`(N, K, S)`, normalized :obj:`log_weights`
    :math:`(N, K)`) before resampling (:obj:`None` for the Gaussian
    trackers). A smoother (a tracker with a :obj:`lag`) adds its window:
    the revised estimates of the steps :math:`t - W + 1, \dots, t`,
    :obj:`window_mean` :math:`(N, W, S)` and :obj:`window_cov`
    :math:`(N, W, S, S)`, the newest last (:obj:`mean` and :obj:`cov`
    are the newest: the filtered estimate), and where nodes joined a live
    session within the window, each node's first step in it
    :obj:`window_start` :math:`(N)` (the rows before hold the prior it
    joined with, no estimate; :obj:`None`: every node is there from the
    window's first step)."""
    t: int
    mean: Tensor
    cov: Tensor
    particles: Optional[Tensor] = None
    log_weights: Optional[Tensor] = None
    window_mean: Optional[Tensor] = None
    window_cov: Optional[Tensor] = None
    window_start: Optional[Tensor] = None


class TrackOutput(NamedTuple):
    r"""Estimates :obj:`mean` :math:`(N, T, S)` and covariances :obj:`cov`
    :math:`(N, T, S, S)` of a whole sequence."""
    mean: Tensor
    cov: Tensor


class Tracker(torch.nn.Module):
    r"""The base of the trackers, which holds a motion and a measurement
    model (the paper's by default) and runs the time loop. Subclasses
    implement :meth:`~tg_nebp.filters.Tracker.steps` (the time loop,
    lazily, one :class:`~tg_nebp.filters.StepOutput` per time step) and
    :meth:`~tg_nebp.filters.Tracker.settings`;
    :meth:`~tg_nebp.filters.Tracker.forward` tracks the whole sequence.

    Args:
        motion (MotionModel, optional): Motion model.
            (default: :obj:`ConstantVelocityDrag()`)
        measurement (MeasurementModel, optional): Measurement model.
            (default: :obj:`GaussianRange()`)
    """
    #: Whether the tracker reads a realization's known inputs
    #: (:obj:`control`); without them every step is the motion model's
    #: input-free prediction (to measure what odometry is worth).
    use_control: bool = True

    def __init__(self, motion: Optional[MotionModel] = None,
                 measurement: Optional[MeasurementModel] = None):
        super().__init__()
        self.motion, self.measurement = resolve_models(motion, measurement)

    def controls_of(self, data: Realization) -> list:
        r"""The known inputs of every step that the tracker reads
        (:meth:`~tg_nebp.data.Realization.controls_by_step`; none where
        :attr:`use_control` is off)."""
        return controls_of(data, self.use_control)

    def check(self, data: Realization) -> None:
        r"""Checks a realization (:func:`~tg_nebp.data.check_realization`
        with the link features the measurement model reads), that its
        states have the motion model's dimension
        (:func:`~tg_nebp.data.check_state_dim`) and that its known inputs,
        if any, are the motion model's
        (:func:`~tg_nebp.data.check_control`)."""
        check_realization(data, self.measurement.features,
                          self.measurement.negative_ranges)
        check_state_dim(data.prior_mean.size(1), self.motion,
                        position_dim_of(data))
        if self.use_control:
            check_control(data, self.motion)

    def steps(self, data: Realization,
              generator=None) -> Iterator[StepOutput]:
        r"""Runs the time loop over a single or batched realization
        lazily, yielding a :class:`StepOutput` per time step; the trackers
        that draw random numbers draw them from :obj:`generator`."""
        raise NotImplementedError

    def initial_state(self, data: Realization, generator=None):
        r"""The state before the first step of the nodes of :obj:`data`
        (its :obj:`prior_mean`, :obj:`prior_cov` and :obj:`anchor`): an
        instance of :attr:`state_type`, drawn from :obj:`generator` where
        the method draws. With :meth:`step` it is what a live
        :class:`~tg_nebp.filters.TrackingSession` needs of a tracker."""
        raise NotImplementedError(f'{type(self).__name__} does not run '
                                  f'live: it defines no initial_state()')

    def step(self, state, edge_index: Tensor, edge_attr: Tensor,
             anchor: Tensor, t: int, generator=None,
             motion: Optional[MotionModel] = None,
             control: Optional[Tensor] = None):
        r"""One time step from :obj:`state` with the links
        :obj:`edge_index` :math:`(2, E)` (sorted by receiver) and their
        features :obj:`edge_attr` :math:`(E, F)`, predicting by
        :obj:`motion` (the tracker's by default) with every node's known
        input :obj:`control` :math:`(N, C)` (a motion model's that takes
        one; NaN rows for none): the step's
        :class:`StepOutput` (time index :obj:`t`) and the state after it.
        The offline loop (:meth:`steps`) and a live session call it
        alike."""
        raise NotImplementedError(f'{type(self).__name__} does not run '
                                  f'live: it defines no step()')

    #: The class of the state that :meth:`initial_state` and :meth:`step`
    #: return (a :class:`~typing.NamedTuple` of tensors; its
    #: :obj:`FIELDS`, a :class:`~tg_nebp.filters.StateField` per field,
    #: say what each may hold).
    state_type = None

    def check_state(self, state, anchor: Tensor, state_size: int,
                    dtype: torch.dtype) -> Dict[str, int]:
        r"""Raises a :class:`ValueError` naming the field of
        :obj:`state` (a saved one) that :meth:`step` could not have
        produced for the nodes of :obj:`anchor` :math:`(N)` with states of
        :obj:`state_size` entries in a session of :obj:`dtype`: every
        field against the :obj:`FIELDS` of :attr:`state_type` (shapes,
        finiteness, covariances symmetric positive semi-definite, weights
        normalized, booleans as booleans; float dtypes and the sizes
        that do not depend on the nodes as :meth:`initial_state` makes
        them). Returns the sizes that the
        fields' dimension names bound (:func:`~tg_nebp.filters.check_state`);
        a tracker adds what ties its fields together. A state type without
        :obj:`FIELDS` is not checked."""
        fields = getattr(self.state_type, 'FIELDS', None)
        if fields is None:
            return {}
        # the dtypes and trailing sizes: those of one node's state afresh
        stand_in = Realization(
            prior_mean=torch.zeros(1, state_size, dtype=dtype),
            prior_cov=torch.eye(state_size, dtype=dtype).unsqueeze(0),
            anchor=torch.zeros(1, dtype=torch.bool), num_nodes=1)
        template = self.initial_state(stand_in, torch.Generator())
        return check_state(state, fields, anchor.numel(), state_size,
                           template)

    def select_state(self, state, keep: Tensor, anchor: Tensor):
        r"""The state of the nodes :obj:`keep` :math:`(N)` (a mask; the
        others leave): every field's rows, here (a tracker whose state
        is not one row per node overrides it). :obj:`anchor` is the mask
        of the nodes before."""
        return type(state)(*(None if field is None else field[keep]
                             for field in state))

    def join_state(self, state, joined):
        r"""The state of the nodes of :obj:`state` followed by those of
        :obj:`joined` (an :meth:`initial_state`): every field's rows
        concatenated, here."""
        return type(state)(*(None if old is None else torch.cat([old, new])
                             for old, new in zip(state, joined)))

    def forward(self, data: Realization, generator=None) -> TrackOutput:
        r"""Tracks a whole (batched) sequence; :obj:`generator` as in
        :meth:`steps`."""
        means, covs = [], []
        for step in self.steps(data, generator):
            means.append(step.mean)
            covs.append(step.cov)
        return TrackOutput(torch.stack(means, 1), torch.stack(covs, 1))

    def settings(self) -> Dict[str, Any]:
        r"""The settings that an evaluation reports next to the accuracy
        (the fields of its :obj:`metrics.json` entry), JSON values."""
        return dict(measurement=self.measurement.config())


class Smoothed(Tracker):
    r"""The smoothed estimates of a smoother :obj:`tracker` (a tracker with
    a :obj:`lag` whose steps carry their window, the :obj:`window_mean`
    of a :class:`StepOutput`): each step's estimate as it leaves the
    window, revised by the measurements of the :math:`L - 1` later steps
    (the last steps of a sequence by those there are), yielded in order
    as soon as it is final. Every metric, figure and table reads it as a
    tracker. A step without a window (the full smoother's, already
    smoothed) passes through unchanged.

    Args:
        tracker (Tracker): The smoother.
    """
    def __init__(self, tracker: Tracker):
        super().__init__(tracker.motion, tracker.measurement)
        self.tracker = tracker

    @property
    def use_control(self) -> bool:
        r"""The smoother's :attr:`Tracker.use_control` (set, it sets the
        smoother's: the steps are its)."""
        return self.tracker.use_control

    @use_control.setter
    def use_control(self, value: bool) -> None:
        self.tracker.use_control = value

    def steps(self, data: Realization,
              generator=None) -> Iterator[StepOutput]:
        r"""The smoothed estimate of every step, in order; the
        :obj:`generator` as the smoother takes it."""
        last = None
        for step in self.tracker.steps(data, generator):
            if step.window_mean is None:
                yield step
                continue
            last = step
            if step.window_mean.size(1) == self.tracker.lag:
                # a full window: its oldest step leaves it
                yield StepOutput(step.t - self.tracker.lag + 1,
                                 step.window_mean[:, 0],
                                 step.window_cov[:, 0])
        if last is None:
            return
        # the rest of the last window is final as it stands
        width = last.window_mean.size(1)
        for k in range(1 if width == self.tracker.lag else 0, width):
            yield StepOutput(last.t - width + 1 + k, last.window_mean[:, k],
                             last.window_cov[:, k])

    def settings(self) -> Dict[str, Any]:
        return dict(self.tracker.settings(), smoothed=True)

    def __repr__(self) -> str:
        return f'{self.__class__.__name__}({self.tracker})'
