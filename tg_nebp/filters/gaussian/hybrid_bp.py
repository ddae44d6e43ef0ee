r"""Hybrid BP: Gaussian belief propagation between the agents (with the
search that relocates an agent whose links decisively put it elsewhere
than its Gaussian belief), and a particle belief within each agent that
keeps the hypotheses a Gaussian cannot."""
import functools
import math
from typing import Any, Dict, Iterator, List, NamedTuple, Optional, Tuple

import torch
from torch import Tensor

from tg_nebp.data.realization import Realization
from tg_nebp.data.validation import check_number, check_positive_int
from tg_nebp.filters.gaussian.fixed_lag_gbp import FixedLagGaussianBP
from tg_nebp.filters.gaussian.gaussian_bp import GaussianBP
from tg_nebp.filters.particle.particle_bp import (Generators,
                                                  _check_prediction, _draw,
                                                  _nodes_per_graph,
                                                  sample_gaussian)
from tg_nebp.filters.gaussian.relocation import LinkSearch, SearchResult
from tg_nebp.filters.particle.resampling import silverman_bandwidth
from tg_nebp.filters.state import StateField, check_state
from tg_nebp.filters.tracker import StepOutput, Tracker
from tg_nebp.gaussian import bounded_inflation_map, graph_index
from tg_nebp.models import MeasurementModel, MotionModel, inputs
from tg_nebp.nn.conv import HybridBPConv
from tg_nebp.nn.conv.hybrid_bp_conv import CHUNK_SIZE
from tg_nebp.utils import log_normalize, symmetrize, weighted_moments

__all__ = ['HybridBP', 'HYBRID_RECOMMENDED', 'PARTICLE_FIELDS',
           'kernel_density']

#: The fields that :class:`HybridBP` adds to its Gaussian tracker's state:
#: every node's :obj:`particles` :math:`(N, K, S)`, their normalized
#: :obj:`log_weights` :math:`(N, K)`, the particle belief's covariance
#: :obj:`particle_cov` :math:`(N, S, S)` and that of the step's predicted
#: particles before the links :obj:`particle_predicted` (what bounds the
#: cloud's inflation; zero before the first step).
PARTICLE_FIELDS = dict(
    particles=StateField(('N', 'K', 'S')),
    log_weights=StateField(('N', 'K'), 'log_weights'),
    particle_cov=StateField(('N', 'S', 'S'), 'cov'),
    particle_predicted=StateField(('N', 'S', 'S'), 'cov'))

#: The best candidates of a search that the proposal draws about.
SEARCH_MODES = 4

#: The configuration of :meth:`~tg_nebp.filters.HybridBP.recommended` (see
#: its docstring).
HYBRID_RECOMMENDED = dict(num_particles=50, proposal=0.7, modes=0.2,
                          spread=1.5)


@functools.lru_cache(maxsize=None)
def _state_type(base: type) -> type:
    # the hybrid state of a Gaussian tracker's state type: its fields, then
    # the particles' (one class per base, named after it)
    fields = list(base._fields) + list(PARTICLE_FIELDS)
    state = NamedTuple(f'Hybrid{base.__name__}', [(f, Any) for f in fields])
    state.FIELDS = dict(base.FIELDS, **PARTICLE_FIELDS)
    return state


def kernel_density(points: Tensor, centers: Tensor, log_weights: Tensor,
                   lower: Tensor, chunk_size: int = 512) -> Tensor:
    r"""The log-density :math:`(N, P)` at :obj:`points` :math:`(N, P, S)`
    of every node's Gaussian mixture :math:`\sum_l w_l \mathcal{N}(
    \mathbf{x}; \mathbf{c}_l, \mathbf{L} \mathbf{L}^\top)` of the
    :obj:`centers` :math:`(N, L, S)` with normalized :obj:`log_weights`
    :math:`(N, L)` and one kernel per node, its Cholesky factor
    :obj:`lower` :math:`(N, S, S)`: both whitened by the kernel once,
    then squared distances (:math:`O(N P L S)`), :obj:`chunk_size` nodes
    at a time (the :math:`(P, L)` distances of a large network's every
    node at once would be fresh memory at every operation)."""
    size = points.size(-1)
    log_norm = (torch.log(lower.diagonal(dim1=-2, dim2=-1)).sum(-1) +
                0.5 * size * math.log(2 * math.pi))
    out = []
    for start in range(0, max(points.size(0), 1), chunk_size):
        nodes = slice(start, start + chunk_size)
        whiten = functools.partial(torch.linalg.solve_triangular,
                                   lower[nodes], upper=False)
        at = whiten(points[nodes].transpose(-1, -2)).transpose(-1, -2)
        of = whiten(centers[nodes].transpose(-1, -2)).transpose(-1, -2)
        squared = torch.cdist(at, of).square()
        out.append(torch.logsumexp(
            log_weights[nodes].unsqueeze(1) - 0.5 * squared, -1))
    return torch.cat(out) - log_norm.unsqueeze(-1)


def _log_gaussian(points: Tensor, mean: Tensor, lower: Tensor) -> Tensor:
    # log N(points (N, P, S); mean (N, S), L L^T) (N, P)
    white = torch.linalg.solve_triangular(
        lower, (points - mean.unsqueeze(1)).transpose(-1, -2),
        upper=False)
    size = points.size(-1)
    return (-0.5 * white.square().sum(-2) -
            torch.log(lower.diagonal(dim1=-2, dim2=-1)).sum(-1,
                                                            keepdim=True) -
            0.5 * size * math.log(2 * math.pi))


class _Prior(NamedTuple):
    # every node's prior of the step as its particles give it: the
    # kernel density's centers (N, K, S), log-weights (N, K) and kernel
    # Cholesky factor (N, S, S), the predicted cloud's covariance
    centers: Tensor
    log_weights: Tensor
    kernel: Tensor
    predicted: Tensor


class HybridBP(Tracker):
    r"""Hybrid belief propagation: the agents exchange the messages of
    Gaussian BP (plain, over a window of steps, or with a learned
    correction: the :obj:`gaussian` tracker, whose estimates it reports),
    while every agent keeps a particle belief of its own, drawn where
    Gaussian BP and the agent's own links put it and weighed by the true
    likelihood of its links, which holds the hypotheses a Gaussian cannot
    (the mirror positions of an agent measured by nodes on a line); an
    agent whose links decisively put it elsewhere than its Gaussian belief
    is relocated there (the Gaussian tracker's
    :class:`~tg_nebp.filters.LinkSearch`), so that no agent stays lost in
    a wrong mode.
    Gaussian-BP-informed proposals for particle BP (`"Neural Enhanced
    Belief Propagation for Cooperative Localization"
    <https://arxiv.org/abs/2105.12903>`_'s particles are too few where a
    belief is sharp) and the multiple-hypothesis re-initialization of
    robotics, in one tracker.

    At every time step:

    1. the Gaussian tracker runs its step
       (:meth:`~tg_nebp.filters.GaussianBP.solve_step`): every agent's
       Gaussian posterior, and the final messages, whose sources'
       extrinsic beliefs the agents' particles read
       (:meth:`~tg_nebp.nn.conv.HybridBPConv.sources`); with its
       :obj:`relocation` (:class:`~tg_nebp.filters.LinkSearch`), every
       agent is searched from its links, and one whose links decisively
       put it elsewhere is **relocated** there: its Gaussian belief starts
       again from that candidate, and so do its particles;
    2. every agent's particles of the last step, their cloud inflated as
       the Gaussian tracker inflates its beliefs (its
       :meth:`~tg_nebp.filters.GaussianBP.inflation_of`, bounded by the
       last step's prediction:
       :func:`~tg_nebp.gaussian.bounded_inflation_map`), are predicted by
       the motion model (each particle its own noise) and smoothed into
       a kernel density :math:`\hat{p}(\mathbf{x})` (a Gaussian kernel of
       :math:`h^2` times the cloud's covariance, Silverman's :math:`h`,
       its centers shrunk towards the mean by :math:`\sqrt{1 - h^2}` so
       that the density keeps the cloud's covariance: Liu and West's
       kernel);
    3. :math:`K` new particles are drawn from the mixture :math:`q` of
       the Gaussian posterior widened by :math:`c` (:obj:`spread`) with
       weight :obj:`proposal`, the same Gaussian about each of the
       ``SEARCH_MODES`` (4) best candidates of the search with weight
       :obj:`modes` (the other hypotheses its links allow), and the prior
       density
       :math:`\hat{p}`, weighted :math:`\hat{p}(\mathbf{x}) /
       q(\mathbf{x})` and then by the messages of the step's links at
       every particle (:class:`~tg_nebp.nn.conv.HybridBPConv`: the exact
       likelihood with the source's extrinsic Gaussian integrated out);
    4. the estimate of every agent is its Gaussian posterior (or the
       relocated Gaussian), with its particle belief in the step's
       :class:`~tg_nebp.filters.StepOutput` (:obj:`particles`,
       :obj:`log_weights`) and, over a window, the window's revisions of
       the past (:obj:`window_mean`, :obj:`window_cov`: the Gaussian
       tracker's).

    The estimates are the Gaussian tracker's (with its relocations), bit
    for bit: the particles keep every agent's non-Gaussian belief beside
    them (its modes, for a figure of the hypotheses or a downstream
    decision), but on the validation realizations they did not beat the
    Gaussian where it stands (the note of issue 47 has the measurements).
    The cost per step is the Gaussian tracker's plus :math:`O(N K^2 S)`
    for the kernel density and :math:`O(|\mathcal{E}| K)` for the
    messages (:math:`O(|\mathcal{E}| K R^2)` for a model without a
    range's closed form). Anchors hold :math:`K` copies of their known
    state.

    Args:
        gaussian (GaussianBP, optional): The Gaussian tracker between the
            agents: a :class:`~tg_nebp.filters.GaussianBP`,
            :class:`~tg_nebp.filters.FixedLagGaussianBP` (its filtered
            estimates) or :class:`~tg_nebp.filters.GaussianNEBP`, whose
            models are the tracker's, and whose :obj:`relocation` relocates
            lost agents (and gives the particles the search's candidates).
            (default: :obj:`GaussianBP.recommended()` with :obj:`motion`,
            :obj:`measurement` and a :class:`~tg_nebp.filters.LinkSearch`)
        num_particles (int, optional): :math:`K` per agent.
            (default: :obj:`50`)
        proposal (float, optional): The share of particles drawn about the
            Gaussian posterior, in :math:`(0, 1)`. (default: :obj:`0.7`)
        modes (float, optional): The share drawn about the search's best
            candidates (the Gaussian posterior's without a search);
            :obj:`proposal` + :obj:`modes` below 1, the rest from the prior
            density. (default: :obj:`0.2`)
        spread (float, optional): :math:`c \ge 1`, the factor of the
            Gaussian posterior's covariance in the proposal.
            (default: :obj:`1.5`)
        bandwidth (float, optional): The kernel's :math:`h \in (0, 1)`;
            :obj:`None` for Silverman's rule
            (:func:`~tg_nebp.filters.silverman_bandwidth`).
            (default: :obj:`None`)
        chunk_size (int, optional): Message edges per block of the
            messages (:class:`~tg_nebp.nn.conv.HybridBPConv`; :obj:`None`
            for all at once). (default: :obj:`4096`)
        motion (MotionModel, optional), measurement (MeasurementModel,
            optional): The models of the default :obj:`gaussian` tracker
            (:obj:`gaussian`'s otherwise).

    Shapes:
        - **input:** a :class:`~tg_nebp.data.Realization`
        - **output:** :class:`~tg_nebp.filters.TrackOutput` with mean
          :math:`(N, T, S)` and covariance :math:`(N, T, S, S)`; every
          step's particles and log-weights in its
          :class:`~tg_nebp.filters.StepOutput`
    """
    def __init__(self, gaussian: Optional[GaussianBP] = None,
                 num_particles: int = 50, proposal: float = 0.7,
                 modes: float = 0.2, spread: float = 1.5,
                 bandwidth: Optional[float] = None,
                 chunk_size: Optional[int] = CHUNK_SIZE,
                 motion: Optional[MotionModel] = None,
                 measurement: Optional[MeasurementModel] = None):
        if gaussian is None:
            gaussian = GaussianBP.recommended(motion=motion,
                                              measurement=measurement,
                                              relocation=LinkSearch())
        elif motion is not None or measurement is not None:
            raise ValueError("'motion' and 'measurement' are those of the "
                             "'gaussian' tracker: give them to it")
        if not isinstance(gaussian, GaussianBP):
            raise TypeError(f"'gaussian' must be a GaussianBP (or a "
                            f"FixedLagGaussianBP, a GaussianNEBP), got "
                            f"{gaussian!r}")
        super().__init__(gaussian.motion, gaussian.measurement)
        self.gaussian = gaussian
        self.num_particles = check_positive_int(num_particles,
                                                'num_particles')
        # without draws about the Gaussian a collapsed cloud stays so;
        # without draws from the prior no other hypothesis is kept
        self.proposal = check_number(proposal, 'proposal')
        self.modes = check_number(modes, 'modes', inclusive=True)
        if self.proposal + self.modes >= 1:
            raise ValueError(f"'proposal' + 'modes' must be below 1 (the "
                             f"rest is drawn from the prior density), got "
                             f"{self.proposal} + {self.modes}")
        self.spread = check_number(spread, 'spread', minimum=1.0,
                                   inclusive=True)
        if bandwidth is not None:
            bandwidth = check_number(bandwidth, 'bandwidth')
            if bandwidth >= 1:
                raise ValueError(f"'bandwidth' must lie in (0, 1), got "
                                 f"{bandwidth}")
        self.bandwidth = bandwidth
        self.conv = HybridBPConv(self.measurement, chunk_size)
        self.state_type = _state_type(gaussian.state_type)

    @classmethod
    def recommended(cls, lag: int = 1, **overrides) -> 'HybridBP':
        r"""Hybrid BP in the configuration of :obj:`HYBRID_RECOMMENDED`
        over :meth:`GaussianBP.recommended()
        <tg_nebp.filters.GaussianBP.recommended>`, or with a :obj:`lag`
        of more than one step over
        :meth:`FixedLagGaussianBP.recommended()
        <tg_nebp.filters.GaussianBP.recommended>` (its filtered
        estimates); :obj:`motion` and :obj:`measurement` among the
        :obj:`overrides` go to that tracker, the others replace the
        hybrid's own settings. Both trackers relocate lost agents
        (:class:`~tg_nebp.filters.LinkSearch` with its defaults, fixed on
        validation realizations before any test realization was
        tracked)."""
        models = {key: overrides.pop(key) for key in ('motion',
                                                      'measurement')
                  if key in overrides}
        lag = check_positive_int(lag, 'lag')
        models['relocation'] = LinkSearch()
        gaussian = (GaussianBP.recommended(**models) if lag == 1 else
                    FixedLagGaussianBP.recommended(lag=lag, **models))
        return cls(gaussian, **{**HYBRID_RECOMMENDED, **overrides})

    def check(self, data: Realization) -> None:
        self.gaussian.check(data)

    # --- the state -----------------------------------------------------

    def _split(self, state) -> Tuple[Any, Tuple[Tensor, ...]]:
        # the Gaussian tracker's state and the particle fields
        size = len(self.gaussian.state_type._fields)
        return self.gaussian.state_type(*state[:size]), tuple(state[size:])

    def initial_state(self, data: Realization, generator: Generators = None):
        r"""The Gaussian tracker's initial state and :math:`K` particles per
        node drawn from the prior (float64; anchors: copies of their
        state), uniform weights."""
        base = self.gaussian.initial_state(data)
        particles = sample_gaussian(
            data.prior_mean.double(), data.prior_cov.double(),
            self.num_particles, generator,
            _nodes_per_graph(data, generator))
        log_weights = particles.new_full(particles.shape[:2],
                                         -math.log(self.num_particles))
        zero = particles.new_zeros(particles.size(0), particles.size(-1),
                                   particles.size(-1))
        return self.state_type(*base, particles, log_weights, zero, zero)

    def check_state(self, state, anchor: Tensor, state_size: int,
                    dtype: torch.dtype) -> Dict[str, int]:
        r"""The Gaussian tracker's checks of its part, the particle
        fields' (``PARTICLE_FIELDS``), and :math:`K` particles per
        node."""
        base, particles = self._split(state)
        sizes = self.gaussian.check_state(base, anchor, state_size, dtype)
        template = self.initial_state(Realization(
            prior_mean=torch.zeros(1, state_size, dtype=dtype),
            prior_cov=torch.eye(state_size, dtype=dtype).unsqueeze(0),
            anchor=torch.zeros(1, dtype=torch.bool), num_nodes=1),
            torch.Generator())
        bound = check_state(_Fields(*particles), PARTICLE_FIELDS,
                            anchor.numel(), state_size,
                            _Fields(*self._split(template)[1]))
        if bound['K'] != self.num_particles:
            raise ValueError(f"the state's 'particles' hold {bound['K']} "
                             f"particles per node, expected "
                             f"{self.num_particles}")
        return dict(sizes, **bound)

    def select_state(self, state, keep: Tensor, anchor: Tensor):
        base, particles = self._split(state)
        return self.state_type(*self.gaussian.select_state(base, keep,
                                                           anchor),
                               *(field[keep] for field in particles))

    def join_state(self, state, joined):
        base, particles = self._split(state)
        new_base, new_particles = self._split(joined)
        return self.state_type(*self.gaussian.join_state(base, new_base),
                               *(torch.cat([old, new]) for old, new in
                                 zip(particles, new_particles)))

    # --- the time loop -------------------------------------------------

    def steps(self, data: Realization,
              generator: Generators = None) -> Iterator[StepOutput]:
        r"""Runs the time loop lazily, yielding a
        :class:`~tg_nebp.filters.StepOutput` per time step (with the
        particles and their log-weights) with the draws from
        :obj:`generator`: one for all nodes, or one per graph of a batch
        (each graph then gets what it gets alone), as
        :class:`~tg_nebp.filters.ParticleBP`."""
        self.check(data)
        counts = _nodes_per_graph(data, generator)
        graph_of = graph_index(data)
        num_graphs = int(graph_of.max()) + 1 if data.num_nodes else 1
        state = self.initial_state(data, generator)
        for t, ((edge_index, edge_attr), control) in enumerate(zip(
                data.edges_by_step(), self.controls_of(data))):
            output, state = self.step(state, edge_index, edge_attr,
                                      data.anchor, t, generator,
                                      graph_of=graph_of,
                                      num_graphs=num_graphs, counts=counts,
                                      control=control)
            yield output

    def step(self, state, edge_index: Tensor, edge_attr: Tensor,
             anchor: Tensor, t: int, generator: Generators = None,
             motion: Optional[MotionModel] = None,
             graph_of: Optional[Tensor] = None, num_graphs: int = 1,
             counts: Optional[List[int]] = None,
             control: Optional[Tensor] = None):
        r"""One time step (see the class): the Gaussian tracker's step,
        the searches and relocations, the particles predicted, drawn and
        weighed. Returns the step's :class:`~tg_nebp.filters.StepOutput`
        and the state after it; :obj:`graph_of` and :obj:`num_graphs` as
        :class:`~tg_nebp.filters.GaussianBP`, :obj:`counts` (the graphs'
        node counts, with one generator per graph) as
        :class:`~tg_nebp.filters.ParticleBP`."""
        base, (particles, log_weights, cov, predicted) = self._split(state)
        first = generator[0] if isinstance(generator, (list, tuple)) else \
            generator
        particles = self._inflated(base, particles, log_weights, cov,
                                   predicted, anchor)
        solved = self.gaussian.solve_step(
            base, edge_index, edge_attr, anchor, t, first, motion, graph_of,
            num_graphs, control)
        edge_index, edge_attr = edge_index.long(), edge_attr.double()
        search = solved.search
        sources = (self.conv.sources(solved.belief, solved.factors,
                                     solved.messages, anchor)
                   if search is None else search.sources)
        prior = self._prior(particles, log_weights, anchor, generator,
                            counts, motion, control, t)
        drawn, log_weights = self._proposed(solved.output, prior, search,
                                            anchor, generator, counts)
        # the links weighed as the Gaussian tracker's messages weigh them
        tempering = (self.gaussian.link_weights(solved, edge_index,
                                                edge_attr, anchor)
                     if search is None else search.tempering)
        log_weights, _ = self.conv(drawn, log_weights, sources,
                                   solved.factors, edge_index, edge_attr,
                                   tempering)
        # the estimates (and a window's revisions of the past) are the
        # Gaussian tracker's
        output = self.gaussian.reported(solved.output, solved.state)._replace(
            particles=drawn, log_weights=log_weights)
        return output, self.state_type(
            *solved.state, drawn, log_weights,
            weighted_moments(drawn, log_weights)[1], prior.predicted)

    def _inflated(self, base, particles: Tensor, log_weights: Tensor,
                  cov: Tensor, predicted: Tensor, anchor: Tensor) -> Tensor:
        # the particles of the last step inflated about their mean as the
        # Gaussian tracker inflates its beliefs (not a fresh prior's), by
        # the factor it gives its own belief: a learned inflation reads
        # the Gaussian's covariance, not that of a cloud that may have
        # collapsed onto a particle
        inflate = ~(base.fresh | anchor)
        if not bool(inflate.any()):
            return particles
        kappa = self.gaussian.inflation_of(base.cov, getattr(base, 'memory',
                                                             None), anchor)
        mapping = bounded_inflation_map(cov, predicted, kappa)
        center = torch.einsum('nk,nks->ns', log_weights.exp(), particles)
        moved = center.unsqueeze(1) + (particles - center.unsqueeze(1)
                                       ) @ mapping.transpose(-1, -2)
        return torch.where(inflate.view(-1, 1, 1), moved, particles)

    def _prior(self, particles: Tensor, log_weights: Tensor, anchor: Tensor,
               generator: Generators, counts: Optional[List[int]],
               motion: Optional[MotionModel], control: Optional[Tensor],
               t: int) -> _Prior:
        # the particles predicted and smoothed into the step's prior
        # density
        motion = self.motion if motion is None else motion

        def predict(part, mask, *rest):
            *given, g = rest
            extra = inputs(given[0].unsqueeze(1).to(part) if given else None)
            moved = motion.sample(part, generator=g, **extra)
            return torch.where(mask.view(-1, 1, 1), part, moved)

        tensors = (particles, anchor) + (() if control is None else
                                         (control, ))
        particles = _draw(predict, generator, counts, *tensors)
        _check_prediction(particles, motion, t)
        mean, cloud = weighted_moments(particles, log_weights)
        size = particles.size(-1)
        h = (silverman_bandwidth(self.num_particles, size)
             if self.bandwidth is None else self.bandwidth)
        # a kernel of h^2 the cloud's covariance, never singular (a cloud
        # on a line, an anchor's point)
        eye = torch.eye(size, dtype=cloud.dtype, device=cloud.device)
        scale = cloud.diagonal(dim1=-2, dim2=-1).mean(-1).clamp_min(1e-12)
        kernel = symmetrize(h * h * cloud) + 1e-9 * scale.view(-1, 1,
                                                               1) * eye
        lower, failed = torch.linalg.cholesky_ex(kernel)
        lower = torch.where((failed != 0).view(-1, 1, 1), eye, lower)
        shrink = math.sqrt(1.0 - h * h)
        centers = shrink * particles + (1 - shrink) * mean.unsqueeze(1)
        return _Prior(centers, log_weights, lower, cloud)

    def _proposed(self, gaussian: StepOutput, prior: _Prior,
                  search: Optional[SearchResult], anchor: Tensor,
                  generator: Generators, counts: Optional[List[int]]
                  ) -> Tuple[Tensor, Tensor]:
        # K draws per agent from q: the Gaussian posterior widened (share
        # 'proposal'), the same about a search's best candidates ('modes',
        # agents searched), the prior density (the rest); weighted p / q.
        # A relocated agent's prior is its new Gaussian, its draws all
        # from it. Anchors keep their copies of the known state
        num, size = self.num_particles, prior.kernel.size(-1)
        eye = torch.eye(size, dtype=prior.kernel.dtype,
                        device=prior.kernel.device)
        lower, failed = torch.linalg.cholesky_ex(
            self.spread * gaussian.cov.to(prior.kernel))
        usable = (failed == 0) & ~anchor
        lower = torch.where(usable.view(-1, 1, 1), lower, eye)
        # the Gaussian's reported (wrapped) angles, and its search's, on
        # the lift of each agent's cloud: the particles of one belief
        # never differ by a turn
        layout = self.motion.layout(size)
        center = torch.einsum('nk,nks->ns', prior.log_weights.exp(),
                              prior.centers)
        mean = layout.nearest(gaussian.mean.to(prior.centers), center)
        if search is None:  # no search: no modes, nobody moved
            search = SearchResult(mean.unsqueeze(1), mean.new_zeros(
                mean.size(0), 1), torch.zeros_like(anchor),
                torch.zeros_like(anchor), None, None)
        moved = search.moved
        count = min(SEARCH_MODES, search.candidates.size(1))
        best = search.scores.topk(count, -1).indices
        modes = layout.nearest(search.candidates.gather(
            1, best.unsqueeze(-1).expand(-1, -1, size)), center.unsqueeze(1))
        mode_share = torch.where(search.searched & usable & ~moved,
                                 self.modes, 0.0)
        gaussian_share = torch.where(moved, 1.0, self.proposal + self.modes
                                     - mode_share)

        def draw(mean, lower, modes, centers, log_weights, kernel,
                 gaussian_share, mode_share, g):
            shape = centers.shape
            like = dict(dtype=centers.dtype, device=centers.device,
                        generator=g)
            noise = torch.randn(shape, **like)
            pick = torch.rand(shape[:2], **like)
            ancestors = torch.multinomial(log_weights.exp(), num,
                                          replacement=True, generator=g)
            which = torch.randint(modes.size(1), shape[:2],
                                  device=centers.device, generator=g)
            spread = noise @ lower.transpose(-1, -2)
            from_kernel = centers.gather(1, ancestors.unsqueeze(-1).expand(
                -1, -1, shape[-1])) + noise @ kernel.transpose(-1, -2)
            from_mode = modes.gather(1, which.unsqueeze(-1).expand(
                -1, -1, shape[-1])) + spread
            gaussian_share, mode_share = (gaussian_share.view(-1, 1),
                                          mode_share.view(-1, 1))
            return torch.where(
                (pick < gaussian_share).unsqueeze(-1),
                mean.unsqueeze(1) + spread, torch.where(
                    (pick < gaussian_share + mode_share).unsqueeze(-1),
                    from_mode, from_kernel))

        drawn = _draw(draw, generator, counts, mean, lower, modes,
                      prior.centers, prior.log_weights, prior.kernel,
                      gaussian_share, mode_share)
        log_kernel = kernel_density(drawn, prior.centers, prior.log_weights,
                                    prior.kernel)
        log_gaussian = _log_gaussian(drawn, mean, lower)
        log_modes = torch.logsumexp(torch.stack(
            [_log_gaussian(drawn, modes[:, c], lower) for c in range(count)],
            -1), -1) - math.log(count)
        shares = torch.stack([gaussian_share, mode_share,
                              1 - gaussian_share - mode_share], -1)
        log_proposal = torch.logsumexp(torch.stack(
            [log_gaussian, log_modes, log_kernel], -1) +
            shares.log().unsqueeze(1), -1)
        # a relocated agent: its prior is its new Gaussian (the proposal)
        log_prior = torch.where(moved.view(-1, 1), log_gaussian, log_kernel)
        # an agent without a usable Gaussian draws from its prior alone
        log_weights = torch.where(usable.view(-1, 1),
                                  log_prior - log_proposal, 0.0)
        drawn = torch.where(anchor.view(-1, 1, 1), prior.centers, drawn)
        log_weights = torch.where(anchor.view(-1, 1), 0.0, log_weights)
        return drawn, log_normalize(log_weights)

    @property
    def lag(self) -> Optional[int]:
        r"""The Gaussian tracker's window :math:`L` (:obj:`None` without
        one): its steps carry the window, which
        :class:`~tg_nebp.filters.Smoothed` reads."""
        return getattr(self.gaussian, 'lag', None)

    def settings(self) -> dict:
        return dict(self.gaussian.settings(), gaussian=type(
            self.gaussian).__name__, particles=self.num_particles,
            proposal=self.proposal, modes=self.modes, spread=self.spread,
            bandwidth=self.bandwidth)

    def __repr__(self) -> str:
        return (f'{self.__class__.__name__}({self.gaussian!r}, '
                f'num_particles={self.num_particles}, '
                f'proposal={self.proposal}, modes={self.modes}, '
                f'spread={self.spread})')


class _Fields(NamedTuple):
    # the particle fields of a hybrid state, as check_state reads them
    particles: Tensor
    log_weights: Tensor
    particle_cov: Tensor
    particle_predicted: Tensor
