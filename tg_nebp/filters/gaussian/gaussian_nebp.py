from typing import Optional

from torch import Tensor

from tg_nebp.data.realization import Realization
from tg_nebp.data.realization import position_dim_of
from tg_nebp.data.validation import check_position_dim
from tg_nebp.filters.gaussian.gaussian_bp import GBP_RECOMMENDED, GaussianBP
from tg_nebp.models import MeasurementModel, MotionModel, model_from_config
from tg_nebp.nn.conv import GaussianNEBPConv

__all__ = ['GaussianNEBP', 'LearnedCorrection']


class LearnedCorrection:
    r"""What a Gaussian tracker with the learned correction
    (:class:`~tg_nebp.nn.conv.GaussianNEBPConv`, its attribute
    :obj:`correction`) adds to its base, shared by :class:`GaussianNEBP` and
    :class:`~tg_nebp.filters.FixedLagGaussianNEBP`: the check of the
    realizations' position dimension, the correction's memory and
    per-agent inflation (times the tracker's :obj:`inflation`), and the
    configuration a checkpoint keeps and rebuilds."""

    #: The entries of the tracker's :obj:`config()` that
    #: :meth:`from_config` may replace: they do not size or feed the
    #: network.
    RUN_TIME_OPTIONS = ('num_iterations', 'tolerance')

    def check(self, data: Realization) -> None:
        r"""The realization checks of every tracker, and that its
        positions have the dimension this correction was built (trained)
        for."""
        super().check(data)
        dim = position_dim_of(data)
        if dim != self.position_dim:
            raise ValueError(f"this {type(self).__name__} was built for "
                             f"{self.position_dim}-D positions, but the "
                             f"realization's are {dim}-D")

    def initial_memory(self, num_nodes: int, device=None) -> Tensor:
        return self.correction.initial_memory(num_nodes, device)

    def inflation_of(self, cov: Tensor, memory: Tensor,
                     anchor: Tensor) -> Tensor:
        r"""Every agent's learned inflation :math:`\kappa_i`
        (:meth:`GaussianNEBPConv.inflation
        <tg_nebp.nn.conv.GaussianNEBPConv.inflation>`) times the
        tracker's :obj:`inflation`."""
        return self.inflation * self.correction.inflation(cov, memory,
                                                          anchor)

    def correction_config(self) -> dict:
        r"""The entries of :obj:`config()` of every corrected tracker:
        :obj:`base` (:obj:`"gaussian"`) tells it from the particle
        :class:`~tg_nebp.filters.NEBP`."""
        correction = self.correction
        return dict(base='gaussian', num_iterations=self.num_iterations,
                    iteration_scale=correction.num_iterations,
                    ends=correction.ends, damping=correction.damping,
                    tolerance=self.tolerance,
                    hidden_dim=correction.hidden_dim,
                    position_dim=self.position_dim,
                    motion=self.motion.config(),
                    measurement=self.measurement.config())

    @staticmethod
    def upgraded_config(config: dict) -> dict:
        r"""A configuration written before :obj:`iteration_scale` existed
        with it at the value it meant (the iterations it was trained
        with); a current one unchanged."""
        return {'iteration_scale': config.get('num_iterations'), **config}

    @classmethod
    def from_config(cls, config: dict, **options):
        r"""Rebuilds a tracker from its :obj:`config()`; :obj:`options` replace
        the entries of :data:`RUN_TIME_OPTIONS` (:obj:`num_iterations`,
        :obj:`tolerance`), which do not size or feed the network; another
        option is a :class:`ValueError` naming it."""
        for name in options:
            if name not in cls.RUN_TIME_OPTIONS:
                raise ValueError(f"'{name}' is fixed by the checkpoint; only "
                                 f"{', '.join(cls.RUN_TIME_OPTIONS)} can be "
                                 f"replaced")
        config = {**cls.upgraded_config(config), **options}
        if config.pop('base', None) != 'gaussian':
            raise ValueError("not the configuration of a Gaussian NEBP")
        motion = model_from_config(config.pop('motion', None), 'motion')
        measurement = model_from_config(config.pop('measurement', None),
                                        'measurement')
        return cls(motion=motion, measurement=measurement, **config)


class GaussianNEBP(LearnedCorrection, GaussianBP):
    r"""Neural Enhanced Gaussian BP: the time loop of
    :class:`~tg_nebp.filters.GaussianBP` (prediction, iterations, early
    stop per graph, float64 beliefs; shared, not copied) with
    :class:`~tg_nebp.nn.conv.GaussianNEBPConv` in place of
    :class:`~tg_nebp.nn.conv.GaussianBPConv`: every message tempered by a
    learned positive weight and every agent's covariance inflated by its
    own learned factor before each prediction, in place of one global
    inflation. Untrained (the output layers at zero) it is plain Gaussian
    BP exactly.

    The node embeddings are carried over iterations and steps (the
    correction's memory of the agents' recent consistency). Training
    (:func:`tg_nebp.training.train` with
    :func:`~tg_nebp.training.gaussian_step_loss`) backpropagates through
    the unrolled iterations of every step; between steps the beliefs and
    memory are detached (truncated in time to one step, as the one
    optimizer step per time step of :func:`~tg_nebp.training.train`
    needs), so a step's loss reaches its own corrections and the
    inflations applied before its prediction.

    Args:
        num_iterations (int, optional): Iterations per time step (at most,
            with :obj:`tolerance`). (default: :obj:`20`)
        motion (MotionModel, optional): Motion model.
            (default: :obj:`ConstantVelocityDrag()`)
        measurement (MeasurementModel, optional): Measurement model inside.
            (default: :obj:`GaussianRange()`)
        ends (str, optional): As in :class:`GaussianBP`.
            (default: :obj:`"both"`)
        damping (float, optional): As in :class:`GaussianBP`.
            (default: :obj:`0.0`)
        tolerance (float, optional): As in :class:`GaussianBP`.
            (default: :obj:`0.01`)
        hidden_dim (int, optional): Size of the correction's embeddings.
            (default: :obj:`32`)
        position_dim (int, optional): The positions' dimension :math:`D`
            the correction is trained for: a tracker (and its checkpoint)
            runs on realizations of that dimension only.
            (default: :obj:`2`)
        iteration_scale (int, optional): What the iteration feature is
            divided by (the iterations the correction was trained with),
            so that running more or fewer iterations than in training shows
            the network the same feature. (default: :obj:`num_iterations`)

    Shapes:
        - **input:** a :class:`~tg_nebp.data.Realization`
        - **output:** :class:`~tg_nebp.filters.TrackOutput` as
          :class:`GaussianBP`'s
    """
    def __init__(self, num_iterations: int = GBP_RECOMMENDED[
                     'num_iterations'],
                 motion: Optional[MotionModel] = None,
                 measurement: Optional[MeasurementModel] = None,
                 ends: str = 'both', damping: float = 0.0,
                 tolerance: Optional[float] = GBP_RECOMMENDED['tolerance'],
                 hidden_dim: int = 32, position_dim: int = 2,
                 iteration_scale: Optional[int] = None):
        super().__init__(num_iterations, motion, measurement, ends, damping,
                         tolerance)
        self.conv = GaussianNEBPConv(
            self.measurement, ends, damping, hidden_dim,
            self.num_iterations if iteration_scale is None else
            iteration_scale)
        self.position_dim = check_position_dim(position_dim)

    @property
    def correction(self) -> GaussianNEBPConv:
        r"""The tracker's conv, which is the learned correction."""
        return self.conv

    def iterate(self, prior, belief, edge_index, edge_attr, anchor,
                messages, generator, factors, memory, iteration):
        r"""One corrected iteration (:meth:`GaussianNEBPConv.forward
        <tg_nebp.nn.conv.GaussianNEBPConv.forward>`): the new beliefs, the
        tempered messages and the memory."""
        return self.conv(prior, belief, edge_index, edge_attr, anchor,
                         memory, messages, generator, factors, iteration,
                         validate=False)

    def link_weights(self, solved, edge_index: Tensor, edge_attr: Tensor,
                     anchor: Tensor) -> Tensor:
        r"""The weights the correction gives the step's message edges at
        its final beliefs, memory and messages, as in its last iteration
        (:meth:`GaussianNEBPConv.weights
        <tg_nebp.nn.conv.GaussianNEBPConv.weights>`): the likelihood its
        tempered messages stand for, to which a search or hybrid BP's
        particles raise each link's (a link it discounts, an NLOS range,
        moves no agent)."""
        if solved.messages is None:  # no link
            return solved.belief.mean.new_zeros(0)
        return self.conv.weights(
            solved.belief, edge_index.long(), edge_attr.double(), anchor,
            solved.state.memory, solved.messages, solved.factors,
            self.num_iterations - 1, validate=False).detach()

    def carry(self, mean: Tensor, cov: Tensor, memory: Tensor,
              predicted: Tensor):
        r"""The beliefs, memory and prediction detached (training is
        truncated in time to one step), the step's consistency added to the
        history."""
        return (mean.detach(), cov.detach(),
                self.conv.end_step(memory.detach()), predicted.detach())

    @classmethod
    def recommended(cls, **overrides) -> 'GaussianNEBP':
        r"""An untrained correction (Gaussian BP without inflation) with
        Gaussian BP's recommended iterations and tolerance; a trained one
        comes from a checkpoint
        (:func:`~tg_nebp.training.gaussian_nebp_from_checkpoint`)."""
        return cls(**{**{key: GBP_RECOMMENDED[key]
                         for key in ('num_iterations', 'tolerance')},
                      **overrides})

    def settings(self) -> dict:
        # the inflation is learned per agent: Gaussian BP's global ones
        # (1) are not this tracker's
        settings = dict(super().settings(), hidden_dim=self.conv.hidden_dim,
                        position_dim=self.position_dim)
        del settings['inflation'], settings['report_inflation']
        return settings

    def config(self) -> dict:
        r"""Everything needed to rebuild this tracker (saved in
        checkpoints, :meth:`LearnedCorrection.from_config
        <tg_nebp.filters.LearnedCorrection.from_config>`)."""
        return self.correction_config()

    def __repr__(self) -> str:
        return (f'{self.__class__.__name__}(num_iterations='
                f'{self.num_iterations}, motion={self.motion}, '
                f'measurement={self.measurement}, ends={self.conv.bp.ends!r}, '
                f'damping={self.conv.bp.damping}, '
                f'tolerance={self.tolerance}, '
                f'hidden_dim={self.conv.hidden_dim}, '
                f'position_dim={self.position_dim})')
