r"""The two model roles of :mod:`tg_nebp`, one base class each (as Stone
Soup has one base per role), on what they share (:class:`Model`, the
registry: :mod:`tg_nebp.models.registry`) and the layout of a state
(:mod:`tg_nebp.models.layout`).

* :class:`MotionModel` samples the transition :math:`p(\mathbf{x}_n |
  \mathbf{x}_{n-1})` and states its state dimension.
* :class:`MeasurementModel` gives :math:`\log p(\mathbf{z}_{j \to i} |
  \mathbf{x}_j, \mathbf{x}_i)` for the link features :math:`\mathbf{z}`
  that it reads (:attr:`~MeasurementModel.features`, the range first) and
  paired sender and receiver particle states, and samples the graph and the
  link features of a scenario.
  :class:`RangeModel` is the measurement model whose likelihood depends on
  the states through the distance only; it gets the memory-light
  coordinate-plane path of :class:`~tg_nebp.nn.conv.ParticleBPConv`.
"""
import copy
import math
from typing import ClassVar, Optional, Tuple

import torch
from torch import Tensor

from tg_nebp.data.validation import check_number
from tg_nebp.gaussian import range_blocks, unit_vectors
from tg_nebp.models.layout import StateLayout
from tg_nebp.models.registry import Model
from tg_nebp.utils import inputs, row_jacobian

# the names this module held before the registry and the layout became
# modules of their own: importable from here for a release, with a warning
# that names where they went
_MOVED = {'MODELS': 'tg_nebp.models.registry',
          'model_like': 'tg_nebp.models.registry',
          'model_from_config': 'tg_nebp.models.registry',
          'wrap_angle': 'tg_nebp.models.layout'}


def __getattr__(name: str):
    if name not in _MOVED:
        raise AttributeError(f"module {__name__!r} has no attribute "
                             f"{name!r}")
    import importlib
    import warnings
    where = _MOVED[name]
    warnings.warn(f"tg_nebp.models.base.{name} moved to {where}.{name} "
                  f"(also tg_nebp.models.{name}); the old place goes in the "
                  f"next release", DeprecationWarning, stacklevel=2)
    return getattr(importlib.import_module(where), name)

__all__ = [
    'MotionModel',
    'MeasurementModel',
    'RangeModel',
    'LinkPairRange',
    'redraw_negative',
    'links_within_range',
]

class MotionModel(Model):
    r"""The motion role: :meth:`~tg_nebp.models.MotionModel.sample` draws
    :math:`\mathbf{x}_n \sim p(\mathbf{x}_n | \mathbf{x}_{n-1},
    \mathbf{u}_n)` for states :math:`(*, S)` and, for a model that takes
    one (:attr:`~tg_nebp.models.MotionModel.control_dim` :math:`C > 0`),
    the step's known input :math:`\mathbf{u}_n` :math:`(*, C)`
    (odometry).

    **The state layout** is the model's to declare (:meth:`layout`): the
    first :math:`D` entries are the position, and some entries may be
    angles. The default is :math:`[\mathbf{p}, \mathbf{v}]` (position,
    then velocity, :math:`D` entries each, :math:`S = 2D`, any :math:`D`,
    read from the states' size); a model for one size only states it in
    :attr:`~tg_nebp.models.MotionModel.state_dim`, and the trackers check
    realizations against it.

    **Known inputs.** A realization may carry every agent's input of every
    step (:obj:`control` :math:`(N, T, C)`); every method passes an
    agent's input to :meth:`sample`, :meth:`mean`, :meth:`jacobian` and
    :meth:`noise_covariance` (keyword :obj:`control`, broadcast against
    the states' leading dimensions). A row of NaN is a step without input
    for that agent: the model's input-free prediction (its own to define,
    documented by the model). A model that takes no input (:math:`C = 0`)
    is never handed one, so its methods need no :obj:`control`
    argument."""
    role = 'motion'
    formula = 'sample'
    #: The state dimension :math:`S` the model is for; :obj:`None` for any
    #: (even) size.
    state_dim: ClassVar[Optional[int]] = None
    #: The width :math:`C` of the known input per agent and step; :obj:`0`
    #: for a model that takes none.
    control_dim: ClassVar[int] = 0

    def layout(self, size: int) -> StateLayout:
        r"""The layout of states of :obj:`size` entries: here the
        position in the first half (:math:`[\mathbf{p}, \mathbf{v}]`), no
        angle. A model of another state overrides it."""
        return StateLayout(size, size // 2)

    def sample(self, states: Tensor,
               generator: Optional[torch.Generator] = None,
               control: Optional[Tensor] = None) -> Tensor:
        r"""Draws the next states :math:`(*, S)` given the states
        :obj:`states` :math:`(*, S)` one time step earlier (and the step's
        input :obj:`control` :math:`(*, C)`, for a model that takes
        one)."""
        raise NotImplementedError

    def mean(self, states: Tensor,
             control: Optional[Tensor] = None) -> Tensor:
        r"""The transition function :math:`f(\mathbf{x}, \mathbf{u})`
        :math:`(*, S)` of a model with additive Gaussian noise,
        :math:`\mathbf{x}_n = f(\mathbf{x}_{n-1}, \mathbf{u}_n) +
        \mathbf{w}_n`, :math:`\mathbf{w}_n \sim \mathcal{N}(\mathbf{0},
        \mathbf{Q}(\mathbf{x}_{n-1}, \mathbf{u}_n))` (noise on a known
        input enters as its linearization, :math:`\mathbf{Q} = \mathbf{G}
        \mathbf{M} \mathbf{G}^\top`): what the Gaussian trackers predict
        with and the bound is computed from. A model that has no such form
        does not define it, and those methods refuse it with this
        error."""
        raise NotImplementedError(
            f"the motion model {self} has no additive-Gaussian-noise form "
            f"(mean() and noise_covariance()): the posterior CRB and the "
            f"Gaussian trackers need one")

    def jacobian(self, states: Tensor,
                 control: Optional[Tensor] = None) -> Tensor:
        r"""The Jacobian :math:`\partial f / \partial \mathbf{x}`
        :math:`(*, S, S)` of :meth:`mean` at :obj:`states` :math:`(*, S)`
        (and :obj:`control`), by automatic differentiation of the model's
        own :meth:`mean` (:func:`~tg_nebp.utils.row_jacobian`: every state
        moves on its own)."""
        given = inputs(control)
        return row_jacobian(
            lambda point: self.mean(point, **given), states,
            states.requires_grad or control is not None and
            control.requires_grad)

    def noise_covariance(self, states: Tensor,
                         control: Optional[Tensor] = None) -> Tensor:
        r"""The covariance :math:`\mathbf{Q}` :math:`(*, S, S)` of the
        additive noise at :obj:`states` :math:`(*, S)` (and
        :obj:`control`; see :meth:`mean`)."""
        raise NotImplementedError(
            f"the motion model {self} has no additive-Gaussian-noise form "
            f"(mean() and noise_covariance()): the posterior CRB and the "
            f"Gaussian trackers need one")

    #: What an input must be for the model to represent it (said where an
    #: input is refused: :meth:`representable`).
    input_limit: ClassVar[str] = 'finite'

    def representable(self, control: Tensor) -> Tensor:
        r"""Whether the model represents each finite known input
        :math:`(*, C)` (a mask :math:`(*)`; NaN rows, no input, are
        :obj:`True`): an input beyond what its noise and linearization
        can stand for (a corrupted odometry row) is refused by name where
        the data meets the model, instead of a broken covariance steps
        later. By default every input."""
        return torch.ones(control.shape[:-1], dtype=torch.bool,
                          device=control.device)

    def linearize(self, states: Tensor, control: Optional[Tensor] = None
                  ) -> Tuple[Tensor, Tensor, Tensor]:
        r"""The transition linearized at :obj:`states` :math:`(*, S)` (and
        :obj:`control`): :math:`f`, :math:`\partial f / \partial
        \mathbf{x}` and :math:`\mathbf{Q}` (:meth:`mean`, :meth:`jacobian`,
        :meth:`noise_covariance`), what every Gaussian method and the bound
        read at each step. By default the three calls; a model whose
        Jacobians come from one pass of its own formula gives all three
        from it."""
        given = inputs(control)
        return (self.mean(states, **given), self.jacobian(states, **given),
                self.noise_covariance(states, **given))

    def measure(self, control: Tensor,
                generator: Optional[torch.Generator] = None) -> Tensor:
        r"""The known inputs :math:`(*, C)` that a sensor (odometry)
        reports for the true inputs :obj:`control` :math:`(*, C)`, with the
        model's own input noise: what a scenario of a model that takes
        inputs records (:meth:`~tg_nebp.datasets.Scenario.generate`)."""
        raise NotImplementedError(f"the motion model {self} takes no "
                                  f"inputs, or does not say how they are "
                                  f"measured (measure())")

    def transition_log_likelihood(self, states: Tensor, moved: Tensor,
                                  control: Optional[Tensor] = None
                                  ) -> Tensor:
        r"""The log-density :math:`(*)` of the transitions from
        :obj:`states` :math:`(*, S)` to :obj:`moved` :math:`(*, S)` (with
        the step's :obj:`control`) under the additive-Gaussian form
        (:meth:`mean`, :meth:`noise_covariance`), on the subspace the
        noise reaches: :math:`-\frac{1}{2} \mathbf{r}^\top \mathbf{Q}^+
        \mathbf{r} - \frac{1}{2} \log \operatorname{pdet}(2 \pi
        \mathbf{Q})` with :math:`\mathbf{r} = \mathbf{x}_n -
        f(\mathbf{x}_{n-1})` (a constant-velocity model's noise has rank
        :math:`D`: a transition off that subspace has no density, and a
        smoothed track's residuals lie on it). What scores a trajectory's
        motion (:class:`~tg_nebp.filters.TrajectorySearch`)."""
        given = inputs(control)
        residual = moved - self.mean(states, **given)
        cov = self.noise_covariance(states, **given)
        values, vectors = torch.linalg.eigh(cov)
        kept = values > 1e-9 * values.amax(-1, keepdim=True).clamp_min(
            torch.finfo(values.dtype).tiny)
        along = (vectors.transpose(-1, -2) @ residual.unsqueeze(-1)
                 ).squeeze(-1)
        safe = torch.where(kept, values, 1.0)
        return -0.5 * torch.where(
            kept, along.square() / safe + torch.log(2 * math.pi * safe),
            0.0).sum(-1)

    def rigidly_moved(self, states: Tensor, rotation: Tensor,
                      offset: Tensor) -> Tensor:
        r"""The :obj:`states` :math:`(*, S)` of a trajectory moved rigidly:
        every position :math:`\mathbf{p} \mapsto \mathbf{R} \mathbf{p} +
        \mathbf{b}` (:obj:`rotation` :math:`(*, D, D)` orthogonal, a
        rotation or a reflection; :obj:`offset` :math:`(*, D)`) and the
        rest of the state as the motion carries it along: here the
        velocity of the default layout :math:`[\mathbf{p}, \mathbf{v}]`,
        :math:`\mathbf{v} \mapsto \mathbf{R} \mathbf{v}`. A model of
        another layout overrides it. What the candidates of a relocation
        with hindsight are made of (:class:`~tg_nebp.filters.TrajectorySearch`,
        which scores them by :meth:`transition_log_likelihood`: a model
        need not be invariant under the move)."""
        dim = self.layout(states.size(-1)).position_dim
        blocks = states.unflatten(-1, (-1, dim)).unsqueeze(-1)
        turned = (rotation.unsqueeze(-3) @ blocks).squeeze(-1).flatten(-2)
        return torch.cat([turned[..., :dim] + offset, turned[..., dim:]], -1)

    def with_time_step(self, dt: float) -> 'MotionModel':
        r"""The same model over a time step of :obj:`dt` seconds, for a
        live session whose steps are not evenly spaced: the model rebuilt
        from its own :meth:`~tg_nebp.models.Model.params` with :obj:`dt`
        replaced (itself where :obj:`dt` is its own). A model without a
        :obj:`dt` parameter cannot move by another time step and says so
        (a :class:`ValueError`); one whose time step is not a parameter
        named :obj:`dt` overrides this method."""
        params = self.params()
        if 'dt' not in params:
            raise ValueError(f"the motion model {self} has no time step "
                             f"'dt' among its parameters: it cannot move "
                             f"by a time step of {dt} s")
        if dt == params['dt']:
            return self
        return type(self)(**{**params, 'dt': dt})


class MeasurementModel(Model):
    r"""The measurement role.

    * :meth:`log_likelihood` :math:`\log p(\mathbf{z}_{j \to i} |
      \mathbf{x}_j^{(k)}, \mathbf{x}_i^{(k)})` :math:`(E, K)` for link
      features :math:`(E, F)` and paired sender and receiver states
      :math:`(E, K, D)`;
    * :attr:`features`: the names of the link features it reads, the
      leading columns of :obj:`edge_attr`, the range first (further columns,
      such as the true NLOS flag of generated data, are carried along);
    * :meth:`scope`: the state entries its likelihood reads (the
      convolutions gather only those);
    * :meth:`connect`, :meth:`sample_links` and :meth:`sample_features`
      generate a scenario's graph and link features.
    """
    role = 'measurement'
    formula = 'log_likelihood'
    #: The names of the link features that the likelihood reads, the
    #: leading columns of :obj:`edge_attr`.
    features: ClassVar[Tuple[str, ...]] = ('range', )
    #: The link features that generation writes, a superset of
    #: :attr:`~MeasurementModel.features`.
    generated_features: ClassVar[Tuple[str, ...]] = ('range', )
    #: Whether the likelihood is defined for a measured range below zero
    #: (a calibrated range between two close nodes is now and then): the
    #: range is then accepted as measured. A model whose likelihood needs
    #: non-negative ranges sets :obj:`False`, and a negative one is
    #: refused by name.
    negative_ranges: ClassVar[bool] = True
    #: The state entries that the likelihood reads; :obj:`None` for all
    #: (see :meth:`scope`).
    state_entries: ClassVar[Optional[Tuple[int, ...]]] = None
    #: The state layout the model reads positions by (:meth:`bind`);
    #: :obj:`None` for :math:`[\mathbf{p}, \mathbf{v}]`, the position in
    #: the first half of a state.
    layout: Optional[StateLayout] = None

    def bind(self, layout: StateLayout) -> 'MeasurementModel':
        r"""The model reading states of :obj:`layout` (the motion model's,
        :meth:`MotionModel.layout`): itself where the layout is the
        default :math:`[\mathbf{p}, \mathbf{v}]`, else a copy that knows
        where the position is. The trackers and the bound bind their
        models (:func:`resolve_models`); the configuration is the
        model's own either way."""
        if layout.position_dim == layout.size // 2 and not layout.angles \
                and self.layout is None:
            return self
        bound = copy.copy(self)
        bound.layout = layout
        return bound

    def position_dim(self, size: int) -> int:
        r"""The number :math:`D` of leading entries of a state of
        :obj:`size` entries that are its position (see :meth:`bind`)."""
        return size // 2 if self.layout is None else self.layout.position_dim

    def log_likelihood(self, z: Tensor, sender: Tensor,
                       receiver: Tensor) -> Tensor:
        r""":math:`\log p(\mathbf{z}_{j \to i} | \mathbf{x}_j^{(k)},
        \mathbf{x}_i^{(k)})` :math:`(E, K)` for link features :obj:`z`
        :math:`(E, F)` and paired states :obj:`sender` and :obj:`receiver`
        :math:`(E, K, D)`."""
        raise NotImplementedError

    def connect(self, pos: Tensor, receiver: Tensor) -> Tensor:
        r"""Returns the measurement edges :obj:`[2, E]` (:math:`j \to i`)
        between nodes at positions :obj:`pos` :math:`(N, D)`, into the
        nodes of the bool mask :obj:`receiver` :math:`(N)`."""
        raise NotImplementedError

    def connect_states(self, states: Tensor, receiver: Tensor) -> Tensor:
        r"""The measurement edges :obj:`[2, E]` between nodes in the true
        states :obj:`states` :math:`(N, S)`, into the :obj:`receiver`
        nodes: :meth:`connect` at their positions. A model whose links
        depend on more than the positions (a sensor's field of view about
        the receiver's heading) overrides it."""
        return self.connect(states[:, :self.position_dim(states.size(-1))],
                            receiver)

    def sample_links(self, num_nodes: int,
                     generator: Optional[torch.Generator] = None):
        r"""The per-link state of a realization (for example which links
        are NLOS), drawn once before its time steps; :obj:`None` (and no
        random draw) for models without one."""
        return None

    def step_links(self, link_state,
                   generator: Optional[torch.Generator] = None):
        r"""The per-link state one time step later (unchanged, and no
        random draw, for models whose links do not switch)."""
        return link_state

    def sample_features(self, states_j: Tensor, states_i: Tensor,
                        link_state, edge_index: Tensor,
                        generator: Optional[torch.Generator] = None
                        ) -> Tensor:
        r"""Link features :math:`(E, F)`
        (:attr:`~MeasurementModel.generated_features`) of the links
        :obj:`edge_index` between true states :obj:`states_j` and
        :obj:`states_i` :math:`(E, D)`."""
        raise NotImplementedError

    def fisher_information(self, z: Tensor, sender: Tensor, receiver: Tensor,
                           generator: Optional[torch.Generator] = None
                           ) -> Tensor:
        r"""The Fisher information :math:`(E, 2D, 2D)` that one measurement
        of every link carries about the stacked states :math:`[\mathbf{x}_j;
        \mathbf{x}_i]` of its two ends, at the states :obj:`sender` and
        :obj:`receiver` :math:`(E, D)`, for links with the features
        :obj:`z` :math:`(E, F)`: the measured values are integrated out
        (a model may read a link's other features, such as a known NLOS
        flag). What the posterior CRB adds for every measurement.

        This generic version is a Monte Carlo of the squared score,
        :math:`\frac{1}{S} \sum_s \mathbf{g}_s \mathbf{g}_s^\top` with
        :math:`\mathbf{g}_s = \nabla \log p(\mathbf{z}_s | \mathbf{x}_j,
        \mathbf{x}_i)` by automatic differentiation of
        :meth:`log_likelihood` and :math:`\mathbf{z}_s` drawn by
        :meth:`sample_features` without a per-link state,
        :attr:`fisher_samples` draws per link; a model whose generation
        needs a per-link state, or that knows a closed form, overrides
        it (:class:`RangeModel` does)."""
        draws = self.fisher_samples
        with torch.enable_grad():
            ends = [x.detach().repeat_interleave(draws, 0).requires_grad_()
                    for x in (sender, receiver)]
            drawn = self.sample_features(*[x.detach() for x in ends], None,
                                         None, generator)
            log_lik = self.log_likelihood(drawn, ends[0].unsqueeze(1),
                                          ends[1].unsqueeze(1))
            scores = torch.autograd.grad(log_lik.sum(), ends)
        score = torch.cat(scores, -1).view(sender.size(0), draws, -1)
        return score.transpose(1, 2) @ score / draws

    #: Draws per link of the Monte Carlo Fisher information
    #: (:meth:`fisher_information`, :meth:`RangeModel.range_information`).
    fisher_samples: ClassVar[int] = 256

    def scope(self, state_dim: int) -> Tuple[int, ...]:
        r"""The entries of a state of size :obj:`state_dim` that the
        likelihood reads (:attr:`state_entries` below :obj:`state_dim`,
        all without them): what the particle convolutions gather, what
        :meth:`linearize` describes, and the scope on each end of a
        Gaussian method's factor."""
        if self.state_entries is None:
            return tuple(range(state_dim))
        return tuple(e for e in self.state_entries if e < state_dim)

    def linearize(self, z: Tensor, sender: Tensor, receiver: Tensor,
                  generator: Optional[torch.Generator] = None
                  ) -> Tuple[Tensor, Tensor]:
        r"""What a Gaussian method (the centralized filter, Gaussian BP)
        uses of one measurement of every link at the states :obj:`sender`
        and :obj:`receiver` :math:`(E, D)`: the gradient :math:`(E, 2R)`
        of :math:`\log p(\mathbf{z} | \mathbf{x}_j, \mathbf{x}_i)` with
        respect to the entries :meth:`scope` of both ends,
        :math:`[\mathbf{x}_{j,r}; \mathbf{x}_{i,r}]`, and a positive
        semi-definite curvature :math:`(E, 2R, 2R)` that stands for its
        negative Hessian there: a Gauss-Newton step treats the link as a
        Gaussian pseudo-measurement with that precision.

        This generic version takes the gradient by automatic
        differentiation of :meth:`log_likelihood` and the Fisher
        information (:meth:`fisher_information`) as the curvature: Fisher
        scoring, exact for a measurement that is linear in the states with
        Gaussian noise. :class:`RangeModel` gives robust weights
        instead."""
        both = self.scope_of_both(sender.size(-1), sender.device)
        info = self.fisher_information(z, sender, receiver, generator)
        return (self.likelihood_gradient(z, sender, receiver)[:, both],
                info[:, both.view(-1, 1), both])

    def likelihood_gradient(self, z: Tensor, sender: Tensor,
                            receiver: Tensor) -> Tensor:
        r"""The gradient :math:`(E, 2S)` of :meth:`log_likelihood` with
        respect to :math:`[\mathbf{x}_j; \mathbf{x}_i]` at the states
        :obj:`sender` and :obj:`receiver` :math:`(E, S)`, by automatic
        differentiation of the model's own formula."""
        with torch.enable_grad():
            ends = [x.detach().requires_grad_() for x in (sender, receiver)]
            log_lik = self.log_likelihood(z, ends[0].unsqueeze(1),
                                          ends[1].unsqueeze(1))
            grads = torch.autograd.grad(log_lik.sum(), ends)
        return torch.cat(grads, -1)

    def scope_of_both(self, size: int, device=None) -> Tensor:
        r"""The indices :math:`(2R)` of the :meth:`scope` entries of both
        ends in :math:`[\mathbf{x}_j; \mathbf{x}_i]` of states of
        :obj:`size` entries."""
        read = torch.tensor(self.scope(size), dtype=torch.long,
                            device=device)
        return torch.cat([read, size + read])


class RangeModel(MeasurementModel):
    r"""A measurement model whose likelihood depends on the states through
    the distance :math:`d = \|\mathbf{p}_j - \mathbf{p}_i\|` only:
    subclasses implement
    :meth:`~tg_nebp.models.RangeModel.log_likelihood_of_distance` (and may
    provide :meth:`~tg_nebp.models.GaussianRange.distance_gradient`, a
    closed-form :math:`\partial \log p / \partial d`, and
    :meth:`~tg_nebp.models.GaussianRange.log_likelihood_of_distance_`, an
    in-place variant, as :class:`~tg_nebp.models.GaussianRange` does).
    Pairs within :obj:`max_range` measure.

    Args:
        max_range (float, optional): Communication range in metres.
            (default: :obj:`20.0`)
    """
    formula = 'log_likelihood_of_distance'

    def __init__(self, max_range: float = 20.0):
        self.max_range = check_number(max_range, 'max_range')

    def log_likelihood_of_distance(self, z: Tensor,
                                   distances: Tensor) -> Tensor:
        r""":math:`\log p(\mathbf{z} | d)` :math:`(E, K)` for link features
        :math:`(E, F)` and distances :math:`(E, K)`."""
        raise NotImplementedError

    def log_likelihood(self, z: Tensor, sender: Tensor,
                       receiver: Tensor) -> Tensor:
        dim = self.position_dim(sender.size(-1))
        return self.log_likelihood_of_distance(
            z, torch.linalg.vector_norm(sender[..., :dim] -
                                        receiver[..., :dim], dim=-1))

    def distance_score(self, z: Tensor, distances: Tensor) -> Tensor:
        r"""The score :math:`\partial \log p(\mathbf{z} | d) / \partial d`
        :math:`(E, K)` at :obj:`distances` :math:`(E, K)`: the model's
        closed-form :obj:`distance_gradient` where it provides one, else
        automatic differentiation of :meth:`log_likelihood_of_distance`
        (differentiable itself either way)."""
        if self.provides('distance_gradient'):
            return self.distance_gradient(z, distances)[0]
        with torch.enable_grad():
            leaf = distances if distances.requires_grad else \
                distances.detach().requires_grad_()
            log_lik = self.log_likelihood_of_distance(z, leaf)
            score, = torch.autograd.grad(log_lik.sum(), leaf,
                                         create_graph=distances.requires_grad)
        return score

    def scope(self, state_dim: int) -> Tuple[int, ...]:
        r"""The positions (:meth:`~MeasurementModel.position_dim`): all
        that a range reads."""
        return tuple(range(self.position_dim(state_dim)))

    def linearize(self, z: Tensor, sender: Tensor, receiver: Tensor,
                  generator: Optional[torch.Generator] = None
                  ) -> Tuple[Tensor, Tensor]:
        r"""The gradient of :math:`\log p(\mathbf{z} | d)` with respect
        to the positions :math:`[\mathbf{p}_j; \mathbf{p}_i]`,
        :math:`s [\mathbf{u}; -\mathbf{u}]`, and the curvature :math:`w
        \nabla d \, \nabla d^\top` with :math:`\nabla d = [\mathbf{u};
        -\mathbf{u}]`, from :meth:`range_linearization` (see
        :meth:`MeasurementModel.linearize`)."""
        unit, score, weights = self.range_linearization(z, sender, receiver)
        # d grows with p_j along u and with p_i against it
        direction = torch.cat([unit, -unit], -1)
        return (score.view(-1, 1) * direction,
                weights.view(-1, 1, 1) * direction.unsqueeze(-1) *
                direction.unsqueeze(-2))

    def range_linearization(self, z: Tensor, sender: Tensor,
                            receiver: Tensor
                            ) -> Tuple[Tensor, Tensor, Tensor]:
        r"""What :meth:`linearize` is made of, one link per row: the unit
        vectors :math:`\mathbf{u}` :math:`(E, P)` from
        :math:`\mathbf{p}_i` to :math:`\mathbf{p}_j` (zero where they
        coincide), the scores :math:`s` :math:`(E)` and the robust weights
        :math:`w` :math:`(E)` (:meth:`robust_weights`) at the distances
        between :obj:`sender` and :obj:`receiver` :math:`(E, D)`. Every
        factor is rank one along :math:`\mathbf{u}`, which lets Gaussian BP
        send scalar messages (:class:`~tg_nebp.nn.conv.RangeMessages`)."""
        dim = self.position_dim(sender.size(-1))
        distances, unit = unit_vectors(sender[:, :dim] - receiver[:, :dim])
        score, weights = self.robust_weights(z, distances.view(-1, 1))
        return unit, score.view(-1), weights.view(-1)

    def robust_weights(self, z: Tensor, distances: Tensor
                       ) -> Tuple[Tensor, Tensor]:
        r"""The scores :math:`s = \partial \log p / \partial d` and the
        weights :math:`w \geq 0` :math:`(E, K)` with which a Gaussian
        method (the centralized filter, Gaussian BP) linearizes this
        likelihood at :obj:`distances`: one Gauss-Newton or iteratively
        reweighted least squares step treats the range as a Gaussian
        pseudo-measurement of precision :math:`w` whose gradient is
        :math:`s`.

        :math:`w = s / r` with the residual :math:`r = z - d` where the
        score points to a zero residual (:math:`s r > 0`): the classical
        IRLS weight, :math:`1 / \sigma^2` for the Gaussian and
        :math:`(\nu + 1) / (\nu \sigma^2 + r^2)` for the Student-t, so an
        outlying range counts little. Elsewhere (a likelihood whose mode is
        not at a zero residual, as the NLOS mixture's, and :math:`r = 0`)
        the observed information :math:`-\partial^2 \log p / \partial
        d^2`, raised to zero where it is negative, as Gauss-Newton drops
        negative curvature. Both come from the model's own formula
        (:meth:`distance_score` and its derivative), or from its closed
        form :obj:`distance_weights` where it provides one
        (:class:`~tg_nebp.models.GaussianRange`,
        :class:`~tg_nebp.models.StudentTRange`)."""
        if self.provides('distance_weights'):
            return self.distance_weights(z, distances)
        with torch.enable_grad():
            leaf = distances.detach().requires_grad_()
            score = self.distance_score(z, leaf)
            curvature, = torch.autograd.grad(-score.sum(), leaf,
                                             allow_unused=True)
        score = score.detach()
        if curvature is None:  # a score that does not depend on d
            curvature = torch.zeros_like(score)
        residual = (z[:, :1] - distances).expand_as(score)
        toward_zero = score * residual > 0
        irls = score / torch.where(toward_zero, residual,
                                   torch.ones_like(residual))
        weights = torch.where(toward_zero, irls, curvature).clamp_min(0.0)
        return score, weights

    def range_information(self, z: Tensor, distances: Tensor,
                          generator: Optional[torch.Generator] = None
                          ) -> Tensor:
        r"""The Fisher information :math:`I(d) = \mathbb{E}_z[(\partial
        \log p(z | d) / \partial d)^2]` :math:`(E)` of one range about the
        distance, at the true :obj:`distances` :math:`(E)` of links with
        features :obj:`z` :math:`(E, F)` (the range is integrated out).
        The model's closed-form :obj:`distance_information` where it
        provides one (:class:`~tg_nebp.models.GaussianRange`:
        :math:`1 / \sigma^2`), else a Monte Carlo of the squared
        :meth:`distance_score` over ranges drawn by :meth:`sample_ranges`
        without a per-link state
        (:attr:`~tg_nebp.models.MeasurementModel.fisher_samples` per link; a
        model
        whose generation needs one provides the closed form)."""
        if self.provides('distance_information'):
            return self.distance_information(z, distances)
        draws = self.fisher_samples
        at = distances.detach().repeat_interleave(draws)
        drawn = self.sample_ranges(at, None, None, generator)
        score = self.distance_score(drawn, at.view(-1, 1))
        return score.view(-1, draws).square().mean(-1)

    def fisher_information(self, z: Tensor, sender: Tensor, receiver: Tensor,
                           generator: Optional[torch.Generator] = None
                           ) -> Tensor:
        r"""The Fisher information :math:`(E, 2D, 2D)` of the range about
        :math:`[\mathbf{x}_j; \mathbf{x}_i]`: :math:`I(d) \mathbf{u}
        \mathbf{u}^\top` on the two position blocks, negated off the
        diagonal, with :math:`\mathbf{u}` the unit vector between the
        positions and :math:`I` from :meth:`range_information`."""
        size = sender.size(-1)
        dim = self.position_dim(size)
        distances, unit = unit_vectors(sender[:, :dim] - receiver[:, :dim])
        return range_blocks(unit, self.range_information(z, distances,
                                                         generator), size)

    def sample_features(self, states_j: Tensor, states_i: Tensor,
                        link_state, edge_index: Tensor,
                        generator: Optional[torch.Generator] = None
                        ) -> Tensor:
        dim = self.position_dim(states_j.size(-1))
        distances = torch.linalg.vector_norm(
            states_j[:, :dim] - states_i[:, :dim], dim=-1)
        return self.sample_ranges(distances, link_state, edge_index,
                                  generator)

    def sample_ranges(self, distances: Tensor, link_state=None,
                      edge_index: Optional[Tensor] = None,
                      generator: Optional[torch.Generator] = None) -> Tensor:
        r"""Link features :math:`(E, F)`
        (:attr:`~MeasurementModel.generated_features`) measured at the true
        :obj:`distances` :math:`(E)` of the links :obj:`edge_index` with the
        per-link state :obj:`link_state` of
        :meth:`~MeasurementModel.sample_links`."""
        raise NotImplementedError

    def connect(self, pos: Tensor, receiver: Tensor,
                block_size: int = 65536) -> Tensor:
        r"""Returns the measurement edges :obj:`[2, E]` (:math:`j \to i`)
        from every node :math:`j` to every :obj:`receiver` node :math:`i
        \neq j` within :obj:`max_range` of it, for positions :obj:`pos`
        :math:`(N, D)`, ordered by sender, then receiver
        (:func:`links_within_range`)."""
        return links_within_range(pos, receiver, self.max_range, block_size)


class LinkPairRange(RangeModel):
    r"""The likelihood of a pair of nodes' two ranges (:math:`z_{j \to i}`
    and :math:`z_{i \to j}`, independent noise) as one factor of the
    distance, :math:`\log p(z_{j \to i} | d) + \log p(z_{i \to j} | d)`
    with :obj:`model`'s own likelihood, for message passing that lets every
    range inform both ends. Its link features are the first range's
    features, the second's, and a flag that the second was measured (an
    anchor's range has none) (:meth:`features_of`). It is composed by the
    trackers, not registered or stored."""
    def __init__(self, model: RangeModel):
        super().__init__(model.max_range)
        self.model = model
        self.layout = model.layout
        self.negative_ranges = model.negative_ranges
        # at least the features the model reads, twice, and the flag; a
        # realization's further columns (generated data's true NLOS flag)
        # ride along
        self.features = ('range', ) + ('feature', ) * (
            2 * len(model.features))

    def params(self) -> dict:
        return dict(model=self.model.config())

    def log_likelihood_of_distance(self, z: Tensor,
                                   distances: Tensor) -> Tensor:
        # the links' feature count F, from the pair's 2 F + 1 columns
        width = (z.size(1) - 1) // 2
        first = self.model.log_likelihood_of_distance(z[:, :width],
                                                      distances)
        second = self.model.log_likelihood_of_distance(
            z[:, width:2 * width], distances)
        measured = z[:, 2 * width:2 * width + 1] > 0.5
        return first + torch.where(measured, second,
                                   torch.zeros_like(second))

    @staticmethod
    def features_of(edge_index: Tensor, edge_attr: Tensor, factor: Tensor,
                    count: int) -> Tensor:
        r"""The link features :math:`(P, 2F + 1)` of :obj:`count` pair
        factors from the links :obj:`edge_index` with features
        :obj:`edge_attr` :math:`(E, F)` and their factor :obj:`factor`
        :math:`(E)`: the first link's features, the second's (the first's
        again where there is none) and the flag."""
        links = torch.arange(factor.numel(), device=factor.device)
        first = torch.full((count, ), factor.numel(), dtype=torch.long,
                           device=factor.device).scatter_reduce_(
                               0, factor, links, 'amin')
        last = torch.full((count, ), -1, dtype=torch.long,
                          device=factor.device).scatter_reduce_(
                              0, factor, links, 'amax')
        measured = (first != last).to(edge_attr.dtype).view(-1, 1)
        return torch.cat([edge_attr[first], edge_attr[last], measured], 1)


def redraw_negative(draw, distances: Tensor) -> Tensor:
    r"""Ranges :obj:`distances + draw(shape)`, redrawing wherever a range
    would be negative (a sensor never reports a negative distance)."""
    ranges = torch.empty_like(distances)
    todo = torch.ones_like(distances, dtype=torch.bool)
    while bool(todo.any()):
        ranges = torch.where(todo, distances + draw(distances.shape), ranges)
        todo = ranges < 0
    return ranges


def links_within_range(pos: Tensor, receiver: Tensor, max_range: float,
                       block_size: int = 65536) -> Tensor:
    r"""The measurement edges :obj:`[2, E]` (:math:`j \to i`)
    from every node :math:`j` to every :obj:`receiver` node :math:`i \neq
    j` within :obj:`max_range` of it, for positions :obj:`pos`
    :math:`(N, D)`, ordered by sender, then receiver.

    A cell list: the nodes are binned into cells a little wider than
    :obj:`max_range`, so that a pair within range lies in the same or
    adjacent cells, and only those pairs are measured: time and memory
    grow linearly with :math:`N` at a fixed density (a dense distance
    matrix grows quadratically). Receivers are handled
    :obj:`block_size` at a time. Every candidate pair's distance is
    computed as :func:`torch.cdist` computes it without its
    matrix-multiplication shortcut (which cancels catastrophically, so
    that pairs at the boundary would flip), so the links are those of
    the dense search exactly."""
    num_nodes, dim = pos.shape
    device = pos.device
    receivers = receiver.nonzero().view(-1)
    if num_nodes == 0 or receivers.numel() == 0:
        return torch.empty(2, 0, dtype=torch.long, device=device)
    # the cell of every node, in float64 with 1 % to spare: rounding
    # never puts a pair within range two cells apart
    width = max_range * 1.01
    scaled = pos.double()
    scaled = scaled - scaled.min(0).values
    if math.isfinite(width):
        scaled = scaled / width
    else:  # one cell holds every node
        scaled = torch.zeros_like(scaled)
    cell = torch.floor(scaled).long() + 1  # +1: room for offset -1
    extent = cell.max(0).values + 2
    strides = torch.cumprod(torch.cat([extent.new_ones(1),
                                       extent[:-1]]), 0)
    key = (cell * strides).sum(-1)
    order = torch.argsort(key, stable=True)
    cells, counts = torch.unique_consecutive(key[order],
                                             return_counts=True)
    starts = torch.cumsum(counts, 0) - counts
    offsets = torch.cartesian_prod(*[torch.tensor(
        [-1, 0, 1], device=device)] * dim).view(-1, dim)
    neighbours = (offsets * strides).sum(-1)  # [3^D]
    blocks = []
    for first in range(0, receivers.numel(), block_size):
        targets = receivers[first:first + block_size]
        wanted = key[targets].unsqueeze(1) + neighbours  # [R, 3^D]
        slot = torch.searchsorted(cells, wanted).clamp_max(
            cells.numel() - 1)
        present = cells[slot] == wanted
        count = torch.where(present, counts[slot], 0).view(-1)
        begin = starts[slot].view(-1)
        # every (receiver, neighbouring cell) run of nodes, expanded
        total = int(count.sum())
        run = torch.repeat_interleave(
            torch.arange(count.numel(), device=device), count)
        within = torch.arange(total, device=device) - (
            torch.cumsum(count, 0) - count)[run]
        senders = order[begin[run] + within]
        ends = targets[run // neighbours.numel()]
        distance = torch.cdist(
            pos[senders].unsqueeze(1), pos[ends].unsqueeze(1),
            compute_mode='donot_use_mm_for_euclid_dist').view(-1)
        keep = (distance <= max_range) & (senders != ends)
        blocks.append(torch.stack([senders[keep], ends[keep]]))
    edges = torch.cat(blocks, dim=1)
    # ordered by sender, then receiver
    return edges[:, torch.argsort(edges[0] * num_nodes + edges[1])]


LOG_SQRT_2PI = 0.5 * math.log(2 * math.pi)
