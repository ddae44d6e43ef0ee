from typing import Optional

from torch import Tensor

from tg_nebp.data.validation import check_position_dim
from tg_nebp.filters.gaussian.fixed_lag_gbp import (WINDOW_GBP_RECOMMENDED,
                                                    FixedLagGaussianBP,
                                                    WindowState)
from tg_nebp.filters.gaussian.gaussian_bp import GBP_RECOMMENDED
from tg_nebp.filters.gaussian.gaussian_nebp import LearnedCorrection
from tg_nebp.models import MeasurementModel, MotionModel
from tg_nebp.nn.conv import GaussianNEBPConv
from tg_nebp.utils import detached

__all__ = ['FixedLagGaussianNEBP']


class FixedLagGaussianNEBP(LearnedCorrection, FixedLagGaussianBP):
    r"""The learned correction of Gaussian NEBP inside the window of
    fixed-lag Gaussian BP, trained through the window's iterations: the
    space-time iterations of :class:`~tg_nebp.filters.FixedLagGaussianBP`
    (every step of the window iterated, each agent's chain solved
    exactly; shared, not copied) with every range message of every window
    step at every iteration tempered by the weight
    :class:`~tg_nebp.nn.conv.GaussianNEBPConv` gives its message edge
    (:meth:`GaussianNEBPConv.corrected_messages
    <tg_nebp.nn.conv.GaussianNEBPConv.corrected_messages>`, general
    messages),

    .. math::
        \tilde{\boldsymbol{\Lambda}}_{f \to (t,k)} = w_{st,k}
        \boldsymbol{\Lambda}_{f \to (t,k)}, \quad
        \tilde{\boldsymbol{\eta}}_{f \to (t,k)} = w_{st,k}
        \boldsymbol{\eta}_{f \to (t,k)},

    and the Gaussian before the window inflated by every agent's learned
    :math:`\kappa_i` times :obj:`inflation` before its prediction.

    Every window row (agent :math:`i` at window step :math:`k`) has its
    own node embedding in the iterations, read from the row's own links
    (its degree, anchors in reach, spread and consistency at that step);
    at each time step every row of an agent starts from the agent's
    memory, and the agent keeps its newest row's (with its consistency
    history, :meth:`GaussianNEBPConv.end_step
    <tg_nebp.nn.conv.GaussianNEBPConv.end_step>`) for the next step and
    for its inflation. Untrained (the output layers at zero) it is
    :meth:`FixedLagGaussianBP.recommended
    <tg_nebp.filters.FixedLagGaussianBP.recommended>` at the same lag with
    every step iterated (at lag 5 or less, the recommended window itself):
    bit for bit its general messages, to rounding the rank-one ones of a
    range model. Training (:func:`tg_nebp.training.train` with
    :func:`~tg_nebp.training.gaussian_window_loss`, Gaussian NEBP's loss
    summed over the window's steps) backpropagates through the unrolled
    iterations of every step; between steps the state is detached
    (truncated in time to one step). :class:`~tg_nebp.filters.Smoothed`
    reads the final estimates, as of every window.

    The correction's inputs are invariant (:class:`GaussianNEBPConv
    <tg_nebp.nn.conv.GaussianNEBPConv>`), so a network trained on small
    windows runs on any. Every step of the window is iterated (no
    settled steps) and the schedule is the sweep (the correction reads
    every message of an iteration).

    Args:
        lag (int, optional): Steps :math:`L` in the window, the newest
            counted. (default: :obj:`5`)
        num_iterations (int, optional): Iterations per time step (at most,
            with :obj:`tolerance`). (default: :obj:`20`)
        motion (MotionModel, optional): Motion model.
            (default: :obj:`ConstantVelocityDrag()`)
        measurement (MeasurementModel, optional): Measurement model inside.
            (default: :obj:`GaussianRange()`)
        ends (str, optional): As in :class:`~tg_nebp.filters.GaussianBP`.
            (default: :obj:`"both"`)
        damping (float, optional): As in
            :class:`~tg_nebp.filters.GaussianBP`. (default: :obj:`0.0`)
        tolerance (float, optional): As in
            :class:`~tg_nebp.filters.GaussianBP`. (default: :obj:`0.01`)
        inflation (float, optional): What the learned inflations multiply
            (the recommended window's). (default: :obj:`1.5`)
        hidden_dim (int, optional): Size of the correction's embeddings.
            (default: :obj:`32`)
        position_dim (int, optional): The positions' dimension :math:`D`
            the correction is trained for. (default: :obj:`2`)
        iteration_scale (int, optional): What the iteration feature is
            divided by (the iterations the correction was trained with).
            (default: :obj:`num_iterations`)

    Shapes:
        - **input:** a :class:`~tg_nebp.data.Realization`
        - **output:** :class:`~tg_nebp.filters.TrackOutput` as
          :class:`~tg_nebp.filters.FixedLagGaussianBP`'s
    """
    def __init__(self, lag: int = 5,
                 num_iterations: int = GBP_RECOMMENDED['num_iterations'],
                 motion: Optional[MotionModel] = None,
                 measurement: Optional[MeasurementModel] = None,
                 ends: str = 'both', damping: float = 0.0,
                 tolerance: Optional[float] = GBP_RECOMMENDED['tolerance'],
                 inflation: float = GBP_RECOMMENDED['inflation'],
                 hidden_dim: int = 32, position_dim: int = 2,
                 iteration_scale: Optional[int] = None):
        super().__init__(lag, num_iterations, motion, measurement, ends,
                         damping, tolerance, inflation)
        self.correction = GaussianNEBPConv(
            self.measurement, ends, damping, hidden_dim,
            self.num_iterations if iteration_scale is None else
            iteration_scale)
        # the window's Gaussian BP is the correction's own
        self.conv = self.correction.bp
        self.position_dim = check_position_dim(position_dim)

    @classmethod
    def recommended(cls, **overrides) -> 'FixedLagGaussianNEBP':
        r"""An untrained correction over the window of
        :meth:`FixedLagGaussianBP.recommended
        <tg_nebp.filters.FixedLagGaussianBP.recommended>` (its iterations,
        tolerance and inflation; every step iterated); a trained one comes
        from a checkpoint
        (:func:`~tg_nebp.training.gaussian_nebp_from_checkpoint`)."""
        return cls(**{**WINDOW_GBP_RECOMMENDED, **overrides})

    @property
    def rank_one(self) -> bool:
        r"""Never: the correction reads and tempers general messages."""
        return False

    def solve_step(self, state: WindowState, *args, **kwargs):
        r""":meth:`FixedLagGaussianBP.solve_step
        <tg_nebp.filters.FixedLagGaussianBP.solve_step>` from the state
        detached (training is truncated in time to one step), the last
        step's consistency added to the agents' history after every step
        (before the first, nothing)."""
        state = detached(state)
        # a window's Gaussian before it stays 'fresh' (the given prior)
        # until its first slide: a step was taken once the window holds one
        if state.window.size(1) > 0 or not bool(state.fresh.all()):
            state = state._replace(
                memory=self.correction.end_step(state.memory))
        return super().solve_step(state, *args, **kwargs)

    def window_messages(self, window, belief, messages, fresh: Tensor,
                        memory: Tensor, iteration: int, generator):
        r"""The corrected messages of every factor of the window in one
        iteration and the rows' memory after it
        (:meth:`GaussianNEBPConv.corrected_messages
        <tg_nebp.nn.conv.GaussianNEBPConv.corrected_messages>`)."""
        return self.correction.corrected_messages(
            belief, window.links, window.link_attr, window.anchor, memory,
            messages, window.factors, iteration, generator, fresh)

    def config(self) -> dict:
        r"""Everything needed to rebuild this tracker (saved in
        checkpoints, :meth:`LearnedCorrection.from_config
        <tg_nebp.filters.LearnedCorrection.from_config>`): the
        correction's, the lag and the inflation its learned ones
        multiply."""
        return dict(self.correction_config(), lag=self.lag,
                    inflation=self.inflation)

    def settings(self) -> dict:
        return dict(super().settings(), hidden_dim=self.correction.hidden_dim,
                    position_dim=self.position_dim)

    def __repr__(self) -> str:
        return (f'{self.__class__.__name__}(lag={self.lag}, num_iterations='
                f'{self.num_iterations}, motion={self.motion}, '
                f'measurement={self.measurement}, ends={self.conv.ends!r}, '
                f'damping={self.conv.damping}, tolerance={self.tolerance}, '
                f'inflation={self.inflation}, '
                f'hidden_dim={self.correction.hidden_dim}, '
                f'position_dim={self.position_dim})')
