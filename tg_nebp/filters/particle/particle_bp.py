import functools
import math
import warnings
from typing import (Callable, Iterator, List, NamedTuple, Optional, Sequence,
                    Tuple, Union)

import torch
from torch import Tensor
from torch_geometric import EdgeIndex
from torch_geometric.data import Batch

from tg_nebp.data.realization import Realization
from tg_nebp.data.validation import (check_layer_inputs, check_number,
                                     check_positive_int, magnitude_limit)
from tg_nebp.filters.particle.resampling import (RESAMPLERS,
                                                 effective_sample_size,
                                                 silverman_bandwidth)
from tg_nebp.filters.state import StateField
from tg_nebp.filters.tracker import StepOutput, Tracker
from tg_nebp.gaussian import bounded_inflation
from tg_nebp.models import (LinkPairRange, MeasurementModel, MotionModel,
                            RangeModel, inputs)
from tg_nebp.nn.conv import ParticleBPConv
from tg_nebp.nn.conv.gaussian_bp_conv import ENDS
from tg_nebp.utils import (compute_dtype, free_memory_bytes, link_factors,
                           log_normalize, long_edge_index, plain_tensor,
                           sort_by_receiver, weighted_moments)

__all__ = ['ParticleBP', 'ParticleState', 'weighted_moments',
           'RECOMMENDED']

Generators = Union[torch.Generator, Sequence[torch.Generator], None]

#: The node-particle arrays of the state that a particle tracker holds at
#: once at least (particles, their prediction, the resampled ones).
PARTICLE_COPIES = 3
#: The largest regularization bandwidth :math:`h` a tracker accepts.
MAX_BANDWIDTH = 10.0
# ParticleBP.recommended(): chosen from the frontier (see its docstring)
RECOMMENDED = dict(num_particles=500, num_samples=32, regularize='silverman',
                   report_inflation=3.0)
#: The largest :obj:`report_inflation` :class:`ParticleBP` accepts.
MAX_REPORT_INFLATION = 10.0


def _nodes_per_graph(data: Realization,
                     generator: Generators) -> Optional[List[int]]:
    # None for a single generator (one draw over all nodes), else the node
    # count of every graph, which must match the generators one to one
    if generator is None or isinstance(generator, torch.Generator):
        return None
    if not (isinstance(generator, (list, tuple)) and all(
            isinstance(g, torch.Generator) for g in generator)):
        raise TypeError(f"'generator' must be a torch.Generator, a list of "
                        f"them (one per graph) or None, got "
                        f"{type(generator).__name__}")
    counts = (data.ptr.diff().tolist() if isinstance(data, Batch) else
              [data.num_nodes])
    if len(generator) != len(counts):
        raise ValueError(f"'generator' holds {len(generator)} generators "
                         f"but the realization has {len(counts)} graphs "
                         f"(one generator per graph, or a single one)")
    return counts


def _draw(draw: Callable, generator: Generators,
          counts: Optional[List[int]], *tensors: Tensor) -> Tensor:
    # draw(*tensors, generator) over all nodes at once, or over every
    # graph's node slice with that graph's generator (concatenated), so that
    # a graph draws the same numbers whatever it is batched with
    if counts is None:
        return draw(*tensors, generator)
    slices = zip(*(tensor.split(counts) for tensor in tensors))
    return torch.cat([draw(*part, g) for part, g in zip(slices, generator)])


def sample_gaussian(mean: Tensor, cov: Tensor, num: int,
                    generator: Generators = None,
                    counts: Optional[List[int]] = None) -> Tensor:
    r""":obj:`num` draws :math:`(N, K, S)` of every node's Gaussian
    :math:`\mathcal{N}(\boldsymbol{\mu}_i, \boldsymbol{\Sigma}_i)`
    (:obj:`mean` :math:`(N, S)`, :obj:`cov` :math:`(N, S, S)`) in the
    dtype of :obj:`mean`, from :obj:`generator` (one, or one per graph of
    node counts :obj:`counts`); a zero covariance (an anchor's) gives
    copies of the mean. A PSD square root, not Cholesky: singular
    covariances are fine."""
    eigvals, eigvecs = torch.linalg.eigh(cov.double())
    root = eigvecs * eigvals.clamp_min(0).sqrt().unsqueeze(-2)

    def standard_normal(mean: Tensor, g: Optional[torch.Generator]):
        return torch.randn((mean.size(0), num, mean.size(-1)),
                           dtype=mean.dtype, device=mean.device, generator=g)

    noise = _draw(standard_normal, generator, counts, mean)
    return mean.unsqueeze(1) + noise @ root.to(noise.dtype).transpose(-1, -2)


def _check_prediction(particles: Tensor, motion, t: int) -> None:
    # an unstable motion model (the explicit quadratic drag beyond
    # |v| = 2 / (drag dt)) would otherwise yield NaN weights first
    limit = magnitude_limit(particles.dtype)
    if bool(particles.abs().amax() <= limit):  # one reduction; NaN fails it
        return
    bad = ~(particles.abs() <= limit).flatten(1).all(-1)
    if bool(bad.any()):
        raise ValueError(f"node {int(bad.nonzero()[0, 0])} at time index "
                         f"{t}: the motion model {motion} predicted states "
                         f"beyond {magnitude_limit(particles.dtype):.3g} or "
                         f"non-finite; its prior or its driving noise makes "
                         f"the motion model diverge")


def _realization_ranges(data: Realization, t: int) -> Callable:
    # the measurements of a node at time index t, named by their rows of
    # the realization (the offline loop's description of a zero belief)
    def describe(node: int) -> str:
        edges = ((data.edge_time == t) &
                 (data.edge_index[1] == node)).nonzero().view(-1)[:3]
        return ', '.join(f"'edge_attr[{e}]' = "
                         f"{float(data.edge_attr[e, 0]):.4g}"
                         for e in edges.tolist())

    return describe


def _check_belief(log_weights: Tensor, t: int, edge_index: Tensor,
                  edge_attr: Tensor,
                  describe: Optional[Callable] = None) -> None:
    # a belief of zero weights cannot be normalized or resampled: name the
    # measurements that caused it rather than let NaNs or an internal field
    # of the resampler reach the user
    zero = torch.isneginf(log_weights).all(-1)
    if not bool(zero.any()):
        return
    i = int(zero.nonzero()[0, 0])
    if describe is None:
        ranges = ', '.join(f'{float(r):.4g}' for r in
                           edge_attr[edge_index[1] == i, 0][:3].tolist())
    else:
        ranges = describe(i)
    raise ValueError(f"node {i} at time index {t}: its measurements ("
                     f"{ranges or 'none'}) give every one of its particles "
                     f"zero likelihood in {log_weights.dtype}; the ranges "
                     f"and the prior of node {i} or its neighbours are "
                     f"irreconcilably far apart for the measurement model")


class ParticleState(NamedTuple):
    r"""What a particle tracker carries from one time step to the next,
    one row per node: the :obj:`particles` :math:`(N, K, S)` and their
    normalized :obj:`log_weights` :math:`(N, K)` of the last step before
    resampling, its weighted covariance :obj:`cov` :math:`(N, S, S)` (the
    regularization's shape), :obj:`fresh` :math:`(N)`: the row holds
    draws of a given prior, which the next step predicts without
    resampling, and the weighted covariance of the step's
    :obj:`predicted` particles :math:`(N, S, S)` before its links (what
    bounds the regularization's inflation; zero before the first step)."""
    particles: Tensor
    log_weights: Tensor
    cov: Tensor
    fresh: Tensor
    predicted: Tensor

    FIELDS = dict(particles=StateField(('N', 'K', 'S')),
                  log_weights=StateField(('N', 'K'), 'log_weights'),
                  cov=StateField(('N', 'S', 'S'), 'cov'),
                  fresh=StateField(('N', ), 'bool'),
                  predicted=StateField(('N', 'S', 'S'), 'cov'))


class ParticleBP(Tracker):
    r"""The particle-based BP tracker for cooperative localization, from the
    `"Neural Enhanced Belief Propagation for Cooperative Localization"
    <https://arxiv.org/abs/2105.12903>`_ paper. For a single or batched
    :class:`~tg_nebp.data.Realization` it draws :math:`K` particles per agent
    from the prior :math:`\mathcal{N}(\boldsymbol{\mu}_{i,0},
    \boldsymbol{\Sigma}_{i,0})` (anchors: :math:`K` copies of their known
    position), then at every time step

    1. predicts :math:`\mathbf{x}_{i,n}^{(k)} \sim p(\mathbf{x}_{i,n} |
       \mathbf{x}_{i,n-1}^{(k)})` (anchors are static),
    2. runs :obj:`num_iterations` message passing iterations
       (:meth:`update`, :class:`~tg_nebp.nn.conv.ParticleBPConv` here),
    3. normalizes the log-weights and computes the MMSE estimate and its
       covariance,
    4. resamples (ancestor indices from :obj:`resampler`, gradient cut):
       every step (the paper), or only the nodes whose effective sample size
       falls below :obj:`ess_threshold` (the others carry their weights
       into the next prediction), with optional regularization (Gaussian
       jitter, :obj:`regularize`); :meth:`resample_step`.

    The randomness (prior, prediction, resampling) comes from
    :obj:`generator`: one :class:`torch.Generator` for the whole batch, or
    one per graph of a batched realization, which makes every graph's
    result independent of what it is batched with (as in distributed
    training, where the realizations of a batch are tracked by different
    processes).

    Subclasses change step 2 only (:class:`NEBP` overrides :meth:`update`):
    the time loop (:meth:`steps`) is shared.

    Args:
        num_particles (int, optional): :math:`K`. (default: :obj:`1000`)
        num_iterations (int, optional): Message passing iterations :math:`T`
            per time step. (default: :obj:`1`)
        motion (MotionModel, optional): Motion model.
            (default: :obj:`ConstantVelocityDrag()`)
        measurement (MeasurementModel, optional): Measurement model; its
            :attr:`~tg_nebp.models.MeasurementModel.features` are the
            link features the realization must hold.
            (default: :obj:`GaussianRange()`)
        resampler (str or callable, optional): :obj:`"multinomial"` (the
            paper's), :obj:`"systematic"`, or a function of
            :obj:`(log_weights, num_samples, generator)` returning indices.
            (default: :obj:`"multinomial"`)
        chunk_size (int, optional): Edge chunk of the convolution.
            (default: :obj:`None`)
        num_samples (int or str, optional): Sender particles :math:`M` per
            receiver particle in every message (see
            :class:`~tg_nebp.nn.conv.ParticleBPConv`): :obj:`1` is the
            paper's pairing, :obj:`"all"` the exact message; the samples are
            drawn from :obj:`generator`. (default: :obj:`1`)
        regularize (float or str, optional): Regularized resampling: after
            resampling, every particle is moved by Gaussian noise with
            covariance :math:`h^2` times the node's weighted particle
            covariance (:math:`0 < h \le 10`), in every direction at most
            what brings the cloud's covariance back to the step's
            prediction (:func:`~tg_nebp.gaussian.bounded_inflation` with
            :math:`\kappa = 1 + h^2`): the kernel widens a belief by
            :math:`1 + h^2` where the links narrowed it at least that
            much, and leaves a direction that no link measured as it is,
            so a node without links (a robot that sees nothing) does not
            grow as :math:`(1 + h^2)^t`; :obj:`"silverman"` takes
            :math:`h` from :func:`~tg_nebp.filters.silverman_bandwidth`
            (about 0.3-0.5 at the paper's :math:`K`).
            (default: :obj:`None`, the paper's plain resampling)
        ess_threshold (float, optional): Resample a node only when its
            effective sample size falls below this fraction of :math:`K`;
            the others carry their weights into the next prediction.
            (default: :obj:`None`, resample every step as the paper)
        compile (bool, optional): Fuse the convolution's per-edge work with
            :func:`torch.compile` (see
            :class:`~tg_nebp.nn.conv.ParticleBPConv`); for BP on CUDA the
            fused Triton kernel is used either way.
            (default: :obj:`False`)
        report_inflation (float, optional): The covariance of every
            estimate it reports is the weighted particle covariance
            inflated by :math:`\kappa_r \geq 1`, no further in any
            direction than the step's predicted cloud's
            (:func:`~tg_nebp.gaussian.bounded_inflation`); the particles,
            their weights and the means are unchanged. A cloud of few
            effective particles is narrower than its errors.
            (default: :obj:`1.0`)

    Shapes:
        - **input:** a :class:`~tg_nebp.data.Realization` with :math:`N`
          nodes and :math:`T` steps
        - **output:** :class:`~tg_nebp.filters.TrackOutput` with mean
          :math:`(N, T, S)` and covariance :math:`(N, T, S, S)`
    """
    state_type = ParticleState

    def __init__(self, num_particles: int = 1000, num_iterations: int = 1,
                 motion: Optional[MotionModel] = None,
                 measurement: Optional[MeasurementModel] = None,
                 resampler: Union[str, Callable] = 'multinomial',
                 chunk_size: Optional[int] = None, compile: bool = False,
                 num_samples: Union[int, str] = 1,
                 regularize: Union[float, str, None] = None,
                 ess_threshold: Optional[float] = None,
                 ends: str = 'receiver', report_inflation: float = 1.0):
        super().__init__(motion, measurement)
        self.report_inflation = check_number(
            report_inflation, 'report_inflation', minimum=1.0,
            inclusive=True, maximum=MAX_REPORT_INFLATION)
        if ends not in ENDS:
            raise ValueError(f"'ends' must be one of {list(ENDS)}, got "
                             f"{ends!r}")
        if ends == 'both' and not isinstance(self.measurement, RangeModel):
            raise TypeError(f"ends='both' shares a range with the node it "
                            f"measured, which needs a likelihood symmetric in "
                            f"the two ends: a RangeModel, not "
                            f"{self.measurement!r}")
        if ends == 'receiver' and num_iterations != 1:
            warnings.warn(
                f"num_iterations={num_iterations} with ends='receiver': "
                f"every iteration sends the senders' beliefs, which already "
                f"hold the receiver's information through the links' "
                f"reverse measurements, so each iteration counts it again "
                f"(overconfident, worse beliefs); ends='both' iterates "
                f"extrinsic messages without the overcount", stacklevel=2)
        self.ends = ends
        if regularize is not None and regularize != 'silverman':
            # a bandwidth is relative to the particle spread: beyond
            # MAX_BANDWIDTH the jitter swamps the belief it regularizes
            regularize = check_number(regularize, 'regularize',
                                      maximum=MAX_BANDWIDTH)
        if ess_threshold is not None:
            ess_threshold = check_number(ess_threshold, 'ess_threshold')
            if ess_threshold > 1:
                raise ValueError(f"'ess_threshold' must lie in (0, 1], got "
                                 f"{ess_threshold}")
        self.regularize = regularize
        self.ess_threshold = ess_threshold
        num_particles = check_positive_int(num_particles, 'num_particles')
        num_iterations = check_positive_int(num_iterations, 'num_iterations')
        if not (isinstance(resampler, str) or callable(resampler)):
            raise TypeError(f"'resampler' must be a name or a callable, got "
                            f"{resampler!r}")
        if isinstance(resampler, str):
            if resampler not in RESAMPLERS:
                raise ValueError(f"'resampler' must be one of "
                                 f"{sorted(RESAMPLERS)} or a callable, got "
                                 f"'{resampler}'")
            resampler = RESAMPLERS[resampler]
        self.num_particles = num_particles
        self.num_iterations = num_iterations
        self.resampler = resampler
        self.conv = ParticleBPConv(self.measurement, chunk_size=chunk_size,
                                   compile=compile, num_samples=num_samples)
        self.num_samples = num_samples
        # ends='both': one factor per pair of nodes, its two ranges'
        # likelihoods summed
        self.pair_conv = (ParticleBPConv(
            LinkPairRange(self.measurement), chunk_size=chunk_size,
            num_samples=num_samples) if ends == 'both' else None)

    @property
    def bp_conv(self) -> ParticleBPConv:
        r"""The :class:`~tg_nebp.nn.conv.ParticleBPConv` that computes the
        BP messages (inside NEBP's layer for :class:`NEBP`)."""
        return self.conv

    @classmethod
    def recommended(cls, **overrides) -> 'ParticleBP':
        r"""The tracker in the configuration chosen from the accuracy-cost
        frontier (:obj:`tg-nebp frontier`): :math:`K = 500` particles,
        :math:`M = 32` sender samples per message, regularized resampling
        with Silverman's bandwidth, multinomial resampling at every step
        (:obj:`RECOMMENDED`). :obj:`overrides` replace or add constructor
        arguments (the motion and measurement models, :obj:`num_particles`,
        ...).

        It was chosen on validation realizations of the paper's test
        network (seed 11, 10 realizations, a 2-core CPU) as the Pareto-
        optimal point within 10 s per realization: :math:`P_\mathrm{out}`
        (1 m) 0.088 and P(accept :math:`H_0`) 0.772 at the 0.95 level in
        4.0 s per realization, against 0.303 and 0.362 for the paper's
        configuration at the same :math:`K`; :math:`M = 64` gained 0.001
        for 1.8 times the time, and every point with more particles was
        worse at about the same or more cost. The paper's configuration
        stays the constructor's default (reproducibility). The frontier was
        measured on the CPU only; on a GPU, where more particles are cheap,
        run the frontier there.

        The reported covariance's :obj:`report_inflation` :math:`\kappa_r
        = 3` (issue 62) was chosen afterwards on 5 validation realizations
        (seed 1) of each of the paper's, the NLOS, the sparse, the
        wide-prior and the 3-D networks: :math:`\kappa_r = 1, 1.5, 2, 3,
        5` gave P(accept 0.95) 0.728, 0.837, 0.881, 0.891, 0.891 (paper),
        0.771, 0.868, 0.901, 0.907, 0.906 (NLOS), 0.518, 0.624, 0.659,
        0.663, 0.664 (sparse), 0.462, 0.564, 0.610, 0.624, 0.627 (wide
        prior) and 0.462, 0.599, 0.660, 0.682, 0.686 (3-D): 3 is the
        smallest within 0.005 of the best worst network (0.627; the bound
        by the predicted cloud saturates it). It changes no estimate."""
        return cls(**{**RECOMMENDED, **overrides})

    def sample_prior(self, data: Realization,
                     generator: Generators = None) -> Tensor:
        r"""Draws :math:`K` particles :math:`(N, K, 4)` from the prior; a
        zero covariance (anchors) gives :math:`K` copies of the mean.

        Args:
            data (Realization): A single or batched realization.
            generator (torch.Generator or [torch.Generator], optional): One
                generator, or one per graph of :obj:`data`.
                (default: :obj:`None`)
        """
        # half precision is drawn in float32 (torch has no half normals on
        # every device, and the filter computes in float32 anyway)
        mean = data.prior_mean.to(compute_dtype(data.prior_mean,
                                                data.prior_cov))
        return sample_gaussian(mean, data.prior_cov, self.num_particles,
                               generator, _nodes_per_graph(data, generator))

    def predict(self, particles: Tensor, anchor: Tensor,
                generator: Optional[torch.Generator] = None,
                motion: Optional[MotionModel] = None,
                control: Optional[Tensor] = None) -> Tensor:
        r"""The prediction step by :obj:`motion` (the tracker's motion
        model by default) with every node's known input :obj:`control`
        :math:`(N, C)` (each particle draws its own noise on it); anchors
        keep their particles."""
        motion = self.motion if motion is None else motion
        given = inputs(None if control is None else
                       control.unsqueeze(1).to(particles.dtype))
        moved = motion.sample(particles, generator=generator, **given)
        return torch.where(anchor.view(-1, 1, 1), particles, moved)

    def update(self, particles: Tensor, log_weights: Tensor,
               edge_index: Tensor, edge_attr: Tensor, anchor: Tensor,
               validate: bool = True,
               sample_offsets: Optional[Tensor] = None) -> Tensor:
        r"""The update step: :obj:`num_iterations` message passing
        iterations (:meth:`iterate`); returns normalized log-weights in
        :obj:`log_weights`' dtype (a learned layer computes in its
        parameters': the state stays of one dtype). Edges
        are summed per receiver, so a plain :obj:`edge_index` is sorted by
        receiver first; :meth:`steps` passes an already sorted
        :class:`~torch_geometric.EdgeIndex` and :obj:`validate=False` (it
        checks the whole realization once) and the offsets of
        :math:`M`-sample messages drawn from its generators (drawn from the
        global generator if :obj:`None`)."""
        if validate:
            check_layer_inputs(particles, log_weights, edge_index, edge_attr,
                               self.measurement.features, anchor,
                               negative_ranges=self.measurement
                               .negative_ranges)
        if self.ends == 'both':
            return self._update_both(particles, log_weights, edge_index,
                                     edge_attr, anchor, sample_offsets)
        # receiver-sorted edges: the convs sum each receiver's segment
        # (deterministic, unlike CUDA's scatter-add) and BP never
        # materializes its [E, K] messages
        edge_index, edge_attr = sort_by_receiver(edge_index,
                                                 particles.size(0), edge_attr)
        sender, state = log_weights, None
        for _ in range(self.num_iterations):
            belief, state = self.iterate(particles, log_weights, edge_index,
                                         edge_attr, anchor, sender, state,
                                         sample_offsets)
            # normalizing scales each message by a per-node constant: the
            # beliefs are unchanged and the log-weights stay bounded
            sender = log_normalize(belief)
        return sender.to(log_weights.dtype)

    def _update_both(self, particles: Tensor, log_weights: Tensor,
                     edge_index: Tensor, edge_attr: Tensor, anchor: Tensor,
                     sample_offsets: Optional[Tensor]) -> Tensor:
        # every pair of nodes one factor (both of its ranges) that informs
        # both ends; each message from the sender's extrinsic belief, its
        # belief without the factor's previous message to it (per particle:
        # within a step the particles stay, only their weights change)
        num_nodes = particles.size(0)
        edge_index = plain_tensor(long_edge_index(edge_index, num_nodes))
        graph = link_factors(edge_index, anchor, 'both')
        features = LinkPairRange.features_of(edge_index, edge_attr,
                                             graph.factor,
                                             graph.ends.size(0))[graph.link]
        index = EdgeIndex(graph.index, sparse_size=(num_nodes, num_nodes),
                          sort_order='col')
        source = graph.index[0]
        has_back = (graph.reverse >= 0).view(-1, 1)
        back = graph.reverse.clamp_min(0)
        belief, messages = log_weights, None
        for _ in range(self.num_iterations):
            weights = belief.index_select(0, source)
            if messages is not None:
                extrinsic = weights - torch.where(has_back, messages[back],
                                                  0.0)
                # a particle that the factor's message ruled out has no
                # weight without it either (-inf - -inf)
                weights = extrinsic.masked_fill(torch.isneginf(weights),
                                                float('-inf'))
            belief, messages = self.pair_conv(
                particles, log_weights, index, features, anchor=anchor,
                validate=False, return_messages=True,
                sample_offsets=sample_offsets,
                edge_sender_log_weights=weights)
            belief = log_normalize(belief)
        return belief

    def iterate(self, particles: Tensor, log_weights: Tensor,
                edge_index: Tensor, edge_attr: Tensor, anchor: Tensor,
                sender_log_weights: Tensor, state=None,
                sample_offsets: Optional[Tensor] = None):
        r"""One message passing iteration: returns the unnormalized belief
        log-weights and a state carried to the next iteration (none for
        BP; NEBP's node embeddings)."""
        belief, _ = self.conv(particles, log_weights, edge_index, edge_attr,
                              sender_log_weights=sender_log_weights,
                              anchor=anchor, validate=False,
                              return_messages=False,
                              sample_offsets=sample_offsets)
        return belief, None

    def check_memory(self, num_nodes: int, state_dim: int,
                     dtype: torch.dtype = torch.float32, device='cpu',
                     free: Optional[int] = None) -> None:
        r"""Refuses, with a :class:`ValueError` naming the sizes, a run whose
        particle arrays do not fit in the free memory of :obj:`device` (or
        :obj:`free` bytes), before any work starts: a lower estimate of
        :obj:`PARTICLE_COPIES` node-particle arrays of the state (the
        particles, their prediction and resampling) and the weights."""
        itemsize = torch.empty((), dtype=dtype).element_size()
        needed = (num_nodes * self.num_particles *
                  (PARTICLE_COPIES * state_dim + 2) * itemsize)
        free = free_memory_bytes(str(device)) if free is None else free
        if needed > free:
            raise ValueError(
                f"{self.num_particles} particles on {num_nodes} nodes need "
                f"at least {needed / 2**30:.3g} GiB, but {free / 2**30:.3g} "
                f"GiB are free on {device}: lower 'particles' or the "
                f"network")

    def steps(self, data: Realization,
              generator: Generators = None) -> Iterator[StepOutput]:
        r"""Runs the time loop lazily, yielding a
        :class:`~tg_nebp.filters.StepOutput` per time step (training takes an
        optimizer step between them): :meth:`step` over the realization's
        links.

        Args:
            data (Realization): A single or batched realization.
            generator (torch.Generator or [torch.Generator], optional): The
                source of every random draw: one generator for all nodes,
                or a sequence of one generator per graph of :obj:`data`
                (graph boundaries from :obj:`data.ptr` for a
                :class:`~torch_geometric.data.Batch`, else a single graph),
                each drawing for its graph's nodes only, so that a graph
                gets the same result alone as in any batch.
                (default: :obj:`None`)
        """
        self.check(data)
        counts = _nodes_per_graph(data, generator)
        # one dtype for the whole loop: half precision is promoted
        state = self.initial_state(data, generator, compute_dtype(
            data.prior_mean, data.prior_cov, data.edge_attr))
        for t, ((edge_index, edge_attr), control) in enumerate(zip(
                data.edges_by_step(), self.controls_of(data))):
            output, state = self.step(state, edge_index, edge_attr,
                                      data.anchor, t, generator,
                                      counts=counts,
                                      describe=_realization_ranges(data, t),
                                      control=control)
            yield output

    def check_state(self, state: ParticleState, anchor: Tensor,
                    state_size: int, dtype: torch.dtype):
        r""":meth:`Tracker.check_state
        <tg_nebp.filters.Tracker.check_state>`, and every node holds
        :obj:`num_particles` particles."""
        sizes = super().check_state(state, anchor, state_size, dtype)
        if sizes['K'] != self.num_particles:
            raise ValueError(f"the state's 'particles' hold {sizes['K']} "
                             f"particles per node, expected "
                             f"{self.num_particles}")
        return sizes

    def initial_state(self, data: Realization,
                      generator: Generators = None,
                      dtype: Optional[torch.dtype] = None) -> ParticleState:
        r"""The state before the first step of the nodes of :obj:`data`
        (its :obj:`prior_mean`, :obj:`prior_cov` and :obj:`anchor` are
        read): :math:`K` particles per node drawn from the prior
        (:meth:`sample_prior`, with :obj:`generator` as there) in
        :obj:`dtype` (the prior's compute type by default), uniform
        weights, every node :obj:`fresh`. A run whose particles do not fit
        in the free memory is refused first (:meth:`check_memory`)."""
        if dtype is None:
            dtype = compute_dtype(data.prior_mean, data.prior_cov)
        self.check_memory(data.num_nodes, data.prior_mean.size(1), dtype,
                          data.prior_mean.device)
        particles = self.sample_prior(data, generator).to(dtype)
        log_weights = particles.new_full(particles.shape[:2],
                                         -math.log(self.num_particles))
        size = particles.size(-1)
        # no step yet: nothing to regularize with
        cov = particles.new_zeros(particles.size(0), size, size)
        return ParticleState(particles, log_weights, cov,
                             torch.ones_like(data.anchor), cov)

    def step(self, state: ParticleState, edge_index: Tensor,
             edge_attr: Tensor, anchor: Tensor, t: int,
             generator: Generators = None,
             motion: Optional[MotionModel] = None,
             counts: Optional[List[int]] = None,
             describe: Optional[Callable] = None,
             control: Optional[Tensor] = None
             ) -> Tuple[StepOutput, ParticleState]:
        r"""One time step, the arithmetic that the offline loop
        (:meth:`steps`) and a live session
        (:class:`~tg_nebp.filters.TrackingSession`) share: the last
        step's particles resampled (:meth:`resample_step`; not a
        :obj:`fresh` prior's), predicted by :obj:`motion` (the tracker's
        by default) with every node's known input :obj:`control`
        :math:`(N, C)`, weighted by the iterations on the links
        :obj:`edge_index` :math:`(2, E)`, features :obj:`edge_attr`
        :math:`(E, F)`, sorted by receiver, and summarized. Returns the
        step's :class:`~tg_nebp.filters.StepOutput` (time index
        :obj:`t`) and the state after it. With one generator per graph,
        :obj:`counts` gives the graphs' node counts; :obj:`describe`
        names a node's measurements in the error of a zero belief."""
        motion = self.motion if motion is None else motion
        particles, log_weights = state.particles, state.log_weights
        if not bool(state.fresh.all()):
            moved, carried = self.resample_step(particles, log_weights,
                                                state.cov, generator, counts,
                                                state.predicted)
            # a prior's draws are predicted as they are, and an anchor's
            # known state is never resampled or jittered: the kernel
            # jitter of a one-point cloud multiplies its rounding-level
            # spread by 1 + h^2 every step (1e18 m after 720 steps of a
            # real sequence)
            fresh = state.fresh.view(-1, 1)
            kept = (state.fresh | anchor).view(-1, 1, 1)
            particles = torch.where(kept, particles, moved)
            log_weights = torch.where(fresh, log_weights, carried)
        num_nodes = particles.size(0)
        # receiver-sorted links: no check, no sort per step
        edge_index = EdgeIndex(edge_index.long(),
                               sparse_size=(num_nodes, num_nodes),
                               sort_order='col')
        if control is None:
            particles = _draw(functools.partial(self.predict, motion=motion),
                              generator, counts, particles, anchor)
        else:  # the inputs split by graph with the particles
            particles = _draw(
                lambda part, mask, given, g: self.predict(part, mask, g,
                                                          motion, given),
                generator, counts, particles, anchor, control)
        _check_prediction(particles, motion, t)
        # the kernel's bound and the reported covariance's: only a tracker
        # that regularizes or inflates what it reports reads it
        predicted = (weighted_moments(particles, log_weights)[1]
                     if self.regularize is not None or
                     self.report_inflation != 1 else state.predicted)
        # the M-sample offsets, per graph from its generator (none drawn
        # for the paper's pairing: its random stream is as is)
        offsets = None
        if self.bp_conv.samples_for(self.num_particles) != 1:
            offsets = _draw(self._draw_offsets, generator, counts, particles)
        log_weights = self.update(particles, log_weights, edge_index,
                                  edge_attr.to(particles.dtype), anchor,
                                  validate=False, sample_offsets=offsets)
        _check_belief(log_weights, t, edge_index, edge_attr, describe)
        mean, cov = weighted_moments(particles, log_weights)
        # the particles' angles stay on the real line (one belief's cloud
        # is contiguous there, so its moments are the arithmetic ones); the
        # reported mean is wrapped
        report = self.motion.layout(mean.size(-1)).wrap(mean)
        # the gradient is cut between steps (resampling): weights carry
        # over as values
        reported = cov if self.report_inflation == 1 else bounded_inflation(
            cov, predicted, cov.new_full(cov.shape[:1],
                                         self.report_inflation))
        return (StepOutput(t, report, reported, particles, log_weights),
                ParticleState(particles, log_weights.detach(), cov.detach(),
                              torch.zeros_like(state.fresh),
                              predicted.detach()))

    def _draw_offsets(self, part: Tensor, g: Optional[torch.Generator]):
        return self.bp_conv.draw_offsets(part.size(0), self.num_particles, g,
                                         part.device)

    def resample_step(self, particles: Tensor, log_weights: Tensor,
                      cov: Tensor, generator: Generators = None,
                      counts: Optional[List[int]] = None,
                      predicted: Optional[Tensor] = None):
        r"""Step 4 of the time loop: resamples the nodes whose effective
        sample size is below :obj:`ess_threshold` :math:`\cdot K` (all
        nodes without a threshold), jitters their particles if
        :obj:`regularize` is set, and returns the particles and the
        log-weights that the next prediction carries (uniform where
        resampled). :obj:`cov` is the weighted particle covariance of the
        step (the jitter's shape), :obj:`predicted` that of its prediction
        before the links (the jitter's bound; :obj:`None`: unbounded). The
        gradient is cut: log-weights carry
        over as values. With one generator per graph, :obj:`counts` gives
        the graphs' node counts (as :meth:`steps` passes them)."""
        def resample(log_weights: Tensor, g: Optional[torch.Generator]):
            return self.resampler(log_weights, self.num_particles, g)

        ancestors = _draw(resample, generator, counts, log_weights)
        resampled = None
        if self.ess_threshold is not None:
            resampled = (effective_sample_size(log_weights) <
                         self.ess_threshold * self.num_particles)
            keep = torch.arange(self.num_particles, device=particles.device)
            ancestors = torch.where(resampled.unsqueeze(-1), ancestors, keep)
        particles = particles.gather(
            1, ancestors.unsqueeze(-1).expand(-1, -1, particles.size(-1)))
        if self.regularize is not None:
            particles = particles + self._jitter(cov, particles, generator,
                                                 counts, resampled, predicted)
        uniform = particles.new_full(particles.shape[:2],
                                     -math.log(self.num_particles))
        if resampled is None:
            return particles, uniform
        return particles, torch.where(resampled.unsqueeze(-1), uniform,
                                      log_weights.to(uniform.dtype))

    def _jitter(self, cov: Tensor, particles: Tensor, generator: Generators,
                counts: Optional[List[int]],
                resampled: Optional[Tensor],
                predicted: Optional[Tensor]) -> Tensor:
        # regularized resampling: Gaussian kernel noise with covariance
        # h^2 times the weighted particle covariance, bounded by the
        # step's prediction (a PSD square root: anchors and collapsed
        # clouds have singular covariances)
        h = (silverman_bandwidth(self.num_particles, particles.size(-1))
             if self.regularize == 'silverman' else self.regularize)
        cov = cov.double()
        if predicted is None:
            kernel = h * h * cov
        else:
            kernel = bounded_inflation(
                cov, predicted.double(),
                cov.new_full(cov.shape[:1], 1 + h * h)) - cov
        eigvals, eigvecs = torch.linalg.eigh(kernel)
        root = (eigvecs * eigvals.clamp_min(0).sqrt().unsqueeze(-2)).to(
            particles.dtype)

        def standard_normal(part: Tensor, g: Optional[torch.Generator]):
            return torch.randn(part.shape, dtype=part.dtype,
                               device=part.device, generator=g)

        noise = _draw(standard_normal, generator, counts, particles)
        jitter = noise @ root.transpose(-1, -2)
        if resampled is not None:  # only the particles just resampled
            jitter = jitter * resampled.view(-1, 1, 1)
        return jitter

    def settings(self) -> dict:
        # the registry's name of the resampler, or a callable's own name
        resampler = next((name for name, known in RESAMPLERS.items()
                          if known is self.resampler),
                         getattr(self.resampler, '__name__',
                                 repr(self.resampler)))
        return dict(particles=self.num_particles,
                    iterations=self.num_iterations,
                    measurement=self.measurement.config(),
                    samples=self.num_samples, regularize=self.regularize,
                    ess_threshold=self.ess_threshold, ends=self.ends,
                    resampler=resampler,
                    report_inflation=self.report_inflation)

    def __repr__(self) -> str:
        options = ''.join(
            f', {name}={getattr(self, name)!r}'
            for name, default in (('num_samples', 1), ('regularize', None),
                                  ('ess_threshold', None))
            if getattr(self, name) != default)
        return (f'{self.__class__.__name__}(num_particles='
                f'{self.num_particles}, num_iterations={self.num_iterations}'
                f', motion={self.motion}, measurement={self.measurement}'
                f'{options})')
