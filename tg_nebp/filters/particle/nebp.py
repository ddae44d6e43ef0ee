from typing import Callable, Optional, Union

from torch import Tensor

from tg_nebp.data.validation import check_position_dim
from tg_nebp.filters.particle.particle_bp import ParticleBP
from tg_nebp.models import (MeasurementModel, MotionModel, StateLayout,
                            model_from_config)
from tg_nebp.nn.conv import EquivariantNEBPConv, NEBPConv, ParticleBPConv

__all__ = ['NEBP', 'VARIANTS']

# the NEBP layers by the name that checkpoints and the CLI use
VARIANTS = {'paper': NEBPConv, 'equivariant': EquivariantNEBPConv}


class NEBP(ParticleBP):
    r"""The Neural Enhanced BP tracker for cooperative localization, from the
    `"Neural Enhanced Belief Propagation for Cooperative Localization"
    <https://arxiv.org/abs/2105.12903>`_ paper: the time loop of
    :class:`~tg_nebp.filters.ParticleBP` (prior, prediction, update,
    estimate, resampling; shared, not copied) with
    :class:`~tg_nebp.nn.conv.NEBPConv` in place of
    :class:`~tg_nebp.nn.conv.ParticleBPConv`. Its learnable parameters are
    those of :obj:`self.conv` (the :class:`~tg_nebp.nn.conv.NEBPConv` in
    place of BP's); train it with :func:`tg_nebp.training.train`
    (the loss :math:`\sum_i \|\hat{\mathbf{p}}_i - \mathbf{p}_i\|^2` at every
    time step; resampling cuts the gradient).

    Args:
        num_particles (int, optional): :math:`K`. (default: :obj:`1000`)
        num_iterations (int, optional): NEBP iterations per time step; more
            than one builds the node update :math:`g_n`. (default: :obj:`1`)
        motion (MotionModel, optional): Motion model.
            (default: :obj:`ConstantVelocityDrag()`)
        measurement (MeasurementModel, optional): Measurement model.
            (default: :obj:`GaussianRange()`)
        resampler (str or callable, optional): See :class:`ParticleBP`.
            (default: :obj:`"multinomial"`)
        message_dim (int, optional): GNN message size. (default: :obj:`32`)
        hidden_dim (int, optional): MLP hidden size. (default: :obj:`64`)
        correct_anchor_edges (bool, optional): Correct the anchors' messages
            too. (default: :obj:`False`)
        chunk_size (int, optional): Edge chunk of the BP messages.
            (default: :obj:`None`)
        num_samples (int or str, optional): Sender particles per receiver
            particle in the BP messages (see :class:`ParticleBP`).
            (default: :obj:`1`)
        regularize (float or str, optional): Regularized resampling (see
            :class:`ParticleBP`). (default: :obj:`None`)
        ess_threshold (float, optional): ESS-adaptive resampling (see
            :class:`ParticleBP`). (default: :obj:`None`)
        compile (bool, optional): Fuse the per-edge work of
            :class:`~tg_nebp.nn.conv.NEBPConv` with :func:`torch.compile`
            (training and inference; not part of :meth:`config`).
            (default: :obj:`False`)
        variant (str, optional): The NEBP layer: :obj:`"paper"`
            (:class:`~tg_nebp.nn.conv.NEBPConv`, sized by :math:`K`) or
            :obj:`"equivariant"`
            (:class:`~tg_nebp.nn.conv.EquivariantNEBPConv`, which runs at
            any :math:`K`: rebuild it with another :obj:`num_particles`).
            (default: :obj:`"paper"`)
        particle_dim (int, optional): Hidden size of the equivariant
            layer's per-particle :math:`g_v`. (default: :obj:`32`)
        position_dim (int, optional): The positions' dimension :math:`D`
            (2 or 3), which sizes the layer: a tracker (and its checkpoint)
            runs on realizations of that dimension only.
            (default: :obj:`2`)

    Shapes:
        - **input:** a :class:`~tg_nebp.data.Realization`
        - **output:** :class:`TrackOutput` with mean :math:`(N, T, 4)` and
          covariance :math:`(N, T, 4, 4)`
    """
    def __init__(self, num_particles: int = 1000, num_iterations: int = 1,
                 motion: Optional[MotionModel] = None,
                 measurement: Optional[MeasurementModel] = None,
                 resampler: Union[str, Callable] = 'multinomial',
                 message_dim: int = 32, hidden_dim: int = 64,
                 correct_anchor_edges: bool = False,
                 chunk_size: Optional[int] = None, compile: bool = False,
                 num_samples: Union[int, str] = 1,
                 regularize: Union[float, str, None] = None,
                 ess_threshold: Optional[float] = None,
                 variant: str = 'paper', particle_dim: int = 32,
                 position_dim: int = 2):
        if variant not in VARIANTS:
            raise ValueError(f"'variant' must be one of {sorted(VARIANTS)}, "
                             f"got {variant!r}")
        super().__init__(num_particles, num_iterations, motion, measurement,
                         resampler, chunk_size, num_samples=num_samples,
                         regularize=regularize, ess_threshold=ess_threshold)
        # the correction's features are a [p, v] state's moments: another
        # layout (a robot's heading) is refused here
        size = self.motion.state_dim
        if size is not None and self.motion.layout(size) != \
                StateLayout(size, size // 2):
            raise ValueError(f"NEBP's learned correction reads [p, v] "
                             f"states; the motion model {self.motion} has "
                             f"{self.motion.layout(size)}: use the Gaussian "
                             f"NEBP (GaussianNEBP), whose features are any "
                             f"layout's")
        self.resampler_name = resampler if isinstance(resampler,
                                                      str) else None
        # the NEBP layer in place of BP's (it holds BP's conv itself)
        layer = dict(message_dim=message_dim, hidden_dim=hidden_dim,
                     correct_anchor_edges=correct_anchor_edges,
                     node_update=num_iterations > 1,
                     measurement=self.measurement, chunk_size=chunk_size,
                     compile=compile, num_samples=num_samples,
                     position_dim=position_dim)
        if variant == 'paper':
            self.conv = NEBPConv(num_particles, **layer)
        else:
            self.conv = EquivariantNEBPConv(particle_dim=particle_dim,
                                            **layer)
        self.variant = variant
        self.particle_dim = particle_dim
        self.position_dim = position_dim
        self.message_dim = message_dim
        self.hidden_dim = hidden_dim
        self.correct_anchor_edges = correct_anchor_edges

    @property
    def bp_conv(self) -> ParticleBPConv:
        return self.conv.bp

    def check(self, data) -> None:
        r"""The realization checks of every tracker, and that its
        positions have the dimension this NEBP was built (trained) for."""
        super().check(data)
        check_position_dim(self.position_dim, data.prior_mean.size(1),
                           'this NEBP')

    def iterate(self, particles: Tensor, log_weights: Tensor,
                edge_index: Tensor, edge_attr: Tensor, anchor: Tensor,
                sender_log_weights: Tensor, state=None,
                sample_offsets: Optional[Tensor] = None):
        return self.conv(particles, log_weights, edge_index, edge_attr,
                         anchor, sender_log_weights=sender_log_weights,
                         embedding=state, validate=False,
                         sample_offsets=sample_offsets)

    def config(self) -> dict:
        r"""Everything needed to rebuild this tracker (saved in
        checkpoints)."""
        if self.resampler_name is None:
            raise ValueError("a tracker with a custom 'resampler' callable "
                             "cannot be saved; pass its name")
        return dict(num_particles=self.num_particles,
                    num_iterations=self.num_iterations,
                    message_dim=self.message_dim, hidden_dim=self.hidden_dim,
                    correct_anchor_edges=self.correct_anchor_edges,
                    resampler=self.resampler_name,
                    num_samples=self.num_samples,
                    regularize=self.regularize,
                    ess_threshold=self.ess_threshold,
                    variant=self.variant,
                    **(dict(particle_dim=self.particle_dim)
                       if self.variant == 'equivariant' else {}),
                    position_dim=self.position_dim,
                    motion=self.motion.config(),
                    measurement=self.measurement.config())

    @staticmethod
    def upgraded_config(config: dict) -> dict:
        r"""A configuration of an older checkpoint with the entries added
        since at the values those checkpoints meant: no :obj:`variant`
        (checkpoint version 2) is the paper's, no :obj:`position_dim` is
        2-D. A current configuration is returned unchanged."""
        return {'variant': 'paper', 'position_dim': 2, **config}

    @classmethod
    def from_config(cls, config: dict, **options) -> 'NEBP':
        r"""Rebuilds a tracker from :meth:`config`; :obj:`options` are
        run-time arguments (:obj:`chunk_size`, :obj:`compile`) or replace
        entries that do not size the GNN (:obj:`num_samples`: the GNN reads
        the BP message, however many sender samples estimate it; and, for
        the equivariant variant, :obj:`num_particles`). A configuration
        without a :obj:`variant` (checkpoint version 2) is the paper's, one
        without :obj:`position_dim` is 2-D."""
        config = {**cls.upgraded_config(config), **options}
        motion = model_from_config(config.pop('motion', None), 'motion')
        measurement = model_from_config(config.pop('measurement', None),
                                        'measurement')
        return cls(motion=motion, measurement=measurement, **config)
