from typing import Any, Iterator, NamedTuple, Optional, Tuple

import torch
from torch import Tensor

from tg_nebp.data.realization import Realization
from tg_nebp.data.validation import check_number, check_positive_int
from tg_nebp.filters.state import StateField
from tg_nebp.filters.tracker import StepOutput, Tracker
from tg_nebp.gaussian import (bounded_inflation, check_predicted_prior,
                              graph_index)
from tg_nebp.models import MeasurementModel, MotionModel, inputs
from tg_nebp.nn.conv.gaussian_bp_conv import (Factors, GaussianBelief,
                                              GaussianBPConv,
                                              as_factor_messages,
                                              tempered_messages)
from tg_nebp.filters.gaussian.noise_adaptation import NoiseAdaptation
from tg_nebp.filters.gaussian.relocation import (LinkSearch, SearchResult,
                                                 relocation_step)
from tg_nebp.nn.conv.hybrid_bp_conv import HybridBPConv
from tg_nebp.utils import symmetrize

__all__ = ['GaussianBP', 'GaussianState', 'SolvedStep', 'GBP_RECOMMENDED']

#: The largest covariance inflation :class:`GaussianBP` accepts.
MAX_INFLATION = 10.0
#: The configuration of :meth:`~tg_nebp.filters.GaussianBP.recommended`,
#: chosen on validation realizations (see its docstring).
GBP_RECOMMENDED = dict(num_iterations=20, tolerance=0.01, inflation=1.5,
                       report_inflation=2.5)


def _inverse(matrices: Tensor) -> Tensor:
    # covariance <-> information of the agents' small blocks, symmetrized
    inverse = torch.linalg.inv(matrices)
    return symmetrize(inverse)


class GaussianState(NamedTuple):
    r"""What a Gaussian BP tracker carries from one time step to the
    next, one row per node: the beliefs' :obj:`mean` :math:`(N, S)` and
    :obj:`cov` :math:`(N, S, S)` (float64; a prior before a node's first
    step), :obj:`fresh` :math:`(N)` (the row holds a given prior, not yet
    predicted: not inflated), the correction's :obj:`memory`
    (:obj:`None` for Gaussian BP) and the step's :obj:`predicted`
    covariance :math:`(N, S, S)` before its links (the prior's before the
    first step), the widest that the inflation makes a belief
    (:func:`~tg_nebp.gaussian.bounded_inflation`)."""
    mean: Tensor
    cov: Tensor
    fresh: Tensor
    memory: Optional[Tensor]
    predicted: Tensor

    FIELDS = dict(mean=StateField(('N', 'S')),
                  cov=StateField(('N', 'S', 'S'), 'cov'),
                  fresh=StateField(('N', ), 'bool'),
                  memory=StateField(('N', '...'), optional=True),
                  predicted=StateField(('N', 'S', 'S'), 'cov'))


class _Active(NamedTuple):
    # the graphs of a batch that still iterate in a time step: their nodes
    # (rows of the batch), prior and current beliefs, links, anchor mask,
    # previous messages, factors, memory, graph of every node and the rows
    # of the step's message edges that its messages are
    nodes: Tensor
    prior: GaussianBelief
    belief: GaussianBelief
    edge_index: Tensor
    edge_attr: Tensor
    anchor: Tensor
    messages: Optional[tuple]
    factors: Factors
    memory: Optional[Tensor]
    graph_of: Tensor
    message_rows: Tensor


def _written(work: _Active, belief: GaussianBelief,
             memory: Optional[Tensor], messages: tuple):
    # the beliefs, memory and messages of the whole batch with those of
    # the graphs that iterate replaced (out of place: gradients flow)
    belief = GaussianBelief(*(full.index_copy(0, work.nodes, part)
                              for full, part in zip(belief, work.belief)))
    if memory is not None:
        memory = memory.index_copy(0, work.nodes, work.memory)
    messages = type(messages)(*(
        full.index_copy(0, work.message_rows, part)
        for full, part in zip(messages, work.messages)))
    return belief, memory, messages


class SolvedStep(NamedTuple):
    r"""A Gaussian tracker's time step with what its iterations ended
    on (:meth:`GaussianBP.solve_step`): the step's :obj:`output` and the
    :obj:`state` after it (what :meth:`~tg_nebp.filters.Tracker.step`
    returns), the step's final beliefs :obj:`belief` in information form
    (one row per node), the :obj:`factors` of the step's links (in the
    nodes' numbering) and the last :obj:`messages` on their message edges
    (:class:`~tg_nebp.nn.conv.RangeMessages` or
    :class:`~tg_nebp.nn.conv.FactorMessages`; :obj:`None` without
    links): what a method that reads Gaussian BP's messages (the sources'
    extrinsic beliefs) needs of the step; and the tracker's
    :obj:`relocation` search of the step (a
    :class:`~tg_nebp.filters.SearchResult`; :obj:`None` without
    one)."""
    output: StepOutput
    state: Any
    belief: GaussianBelief
    factors: Factors
    messages: Optional[tuple]
    search: Optional[SearchResult] = None


class GaussianBP(Tracker):
    r"""The Gaussian belief propagation tracker: every agent keeps a
    Gaussian belief over its own state only (no joint, no cross-agent
    covariances), and at every time step

    1. predicts it with the motion model's mean and Jacobian
       (:math:`\boldsymbol{\mu}^- = f(\boldsymbol{\mu})`,
       :math:`\boldsymbol{\Sigma}^- = \mathbf{F} \boldsymbol{\Sigma}
       \mathbf{F}^\top + \mathbf{Q}`),
    2. runs :obj:`num_iterations` iterations of
       :class:`~tg_nebp.nn.conv.GaussianBPConv` on the step's links, each
       relinearizing every range factor at the current beliefs and sending
       extrinsic messages to both ends of every link (or, with
       :obj:`ends="receiver"`, to the measuring agent only),
    3. reports every agent's belief (mean and covariance).

    Messages start afresh at every step (the factors are new). The cost
    per iteration is :math:`O(|\mathcal{E}| S^3)` with no :math:`K` and no
    joint: the method scales to networks the centralized filter cannot
    hold. Float64 inside. Its best is the centralized filter that keeps
    marginals only (:class:`~tg_nebp.filters.CentralizedIEKF` with
    :obj:`marginal=True`), which it approaches as the iterations
    converge.

    Args:
        num_iterations (int, optional): Message passing iterations :math:`L`
            per time step (at most, with :obj:`tolerance`).
            (default: :obj:`20`)
        motion (MotionModel, optional): Motion model with an
            additive-Gaussian-noise form.
            (default: :obj:`ConstantVelocityDrag()`)
        measurement (MeasurementModel, optional): Measurement model.
            (default: :obj:`GaussianRange()`)
        ends (str, optional): :obj:`"both"` or :obj:`"receiver"` (see
            :class:`~tg_nebp.nn.conv.GaussianBPConv`).
            (default: :obj:`"both"`)
        damping (float, optional): Message damping in :math:`[0, 1)`.
            (default: :obj:`0.0`)
        tolerance (float, optional): Stop a graph's iterations of a step
            early once none of its belief means moved by more than this in
            an iteration (metres, metres per second); every graph of a
            batch stops on its own, so a batch gives what each graph gives
            alone. :obj:`None` runs all :obj:`num_iterations`.
            (default: :obj:`0.01`)
        inflation (float, optional): Every agent's belief covariance is
            multiplied by :math:`\kappa \geq 1` before the next prediction
            (not the prior's, before the first), in every direction no
            further than the step's own prediction
            (:func:`~tg_nebp.gaussian.bounded_inflation`: a direction that
            no link measured is not inflated, so it never grows beyond
            what the motion model adds). This compensates the cross-agent
            correlations that a filter of marginals drops (they make its
            beliefs overconfident, and every later step counts shared
            information again); :obj:`1` is plain Gaussian BP.
            (default: :obj:`1.0`)
        compile (bool, optional): Fuse the rank-one messages of a range
            model with :func:`torch.compile` (see
            :class:`~tg_nebp.nn.conv.GaussianBPConv`; the first steps
            compile). (default: :obj:`False`)
        relocation (LinkSearch, optional): Search every agent from its
            links at every step and start again the lost ones where their
            links decisively put them
            (:class:`~tg_nebp.filters.LinkSearch`); :obj:`None` never
            does. (default: :obj:`None`)
        report_inflation (float, optional): The covariance of every
            estimate it reports is its belief's inflated by
            :math:`\kappa_r \geq 1`, no further in any direction than
            the step's prediction
            (:func:`~tg_nebp.gaussian.bounded_inflation`, as
            :obj:`inflation`); what it carries to
            the next step, and every mean, is unchanged. The beliefs of a
            filter of marginals are narrower than their errors (the
            information that links share is counted again at every
            iteration); :obj:`inflation` is chosen for the accuracy of the
            next steps, this for the honesty of the covariance reported.
            :obj:`1` reports the belief itself. (default: :obj:`1.0`)
        noise_adaptation (NoiseAdaptation, optional): Estimate every
            agent's measurement noise scale from its links' innovations and
            temper its incoming messages by it
            (:class:`~tg_nebp.filters.NoiseAdaptation`): a model whose
            noise is too small for the data is corrected without ground
            truth. :obj:`None` takes the model as it is.
            (default: :obj:`None`)

    Shapes:
        - **input:** a :class:`~tg_nebp.data.Realization`
        - **output:** :class:`~tg_nebp.filters.TrackOutput` with mean
          :math:`(N, T, S)` and covariance :math:`(N, T, S, S)` (anchors:
          their known state, zero covariance)
    """
    state_type = GaussianState

    def __init__(self, num_iterations: int = 20,
                 motion: Optional[MotionModel] = None,
                 measurement: Optional[MeasurementModel] = None,
                 ends: str = 'both', damping: float = 0.0,
                 tolerance: Optional[float] = 0.01, inflation: float = 1.0,
                 compile: bool = False,
                 relocation: Optional[LinkSearch] = None,
                 report_inflation: float = 1.0,
                 noise_adaptation: Optional[NoiseAdaptation] = None):
        super().__init__(motion, measurement)
        if noise_adaptation is not None and not isinstance(
                noise_adaptation, NoiseAdaptation):
            raise TypeError(f"'noise_adaptation' must be a NoiseAdaptation "
                            f"or None, got {noise_adaptation!r}")
        self.noise_adaptation = noise_adaptation
        self.report_inflation = check_number(
            report_inflation, 'report_inflation', minimum=1.0,
            inclusive=True, maximum=MAX_INFLATION)
        self.num_iterations = check_positive_int(num_iterations,
                                                 'num_iterations')
        self.tolerance = (None if tolerance is None else
                          check_number(tolerance, 'tolerance'))
        # beyond MAX_INFLATION the prior of every step is all but flat
        self.inflation = check_number(inflation, 'inflation', minimum=1.0,
                                      inclusive=True, maximum=MAX_INFLATION)
        self.conv = GaussianBPConv(self.measurement, ends, damping, compile)
        self.relocate_with(relocation)

    #: Whether the tracker keeps a window of steps (what a
    #: :class:`~tg_nebp.filters.TrajectorySearch` searches).
    has_window = False

    def relocate_with(self, relocation: Optional[LinkSearch]
                      ) -> 'GaussianBP':
        r"""Sets the tracker's :obj:`relocation` (see the class; a
        :class:`~tg_nebp.filters.LinkSearch`, a window's
        :class:`~tg_nebp.filters.TrajectorySearch`, or :obj:`None`) and returns
        it: a tracker built elsewhere (from a checkpoint) takes one too."""
        if relocation is not None and not isinstance(relocation,
                                                     LinkSearch):
            raise TypeError(f"'relocation' must be a LinkSearch or None, "
                            f"got {relocation!r}")
        if relocation is not None and relocation.needs_window and \
                not self.has_window:
            raise ValueError(f"'relocation' {relocation!r} searches a "
                             f"window's trajectories: {type(self).__name__} "
                             f"has no window (a FixedLagGaussianBP has; here "
                             f"a LinkSearch searches each step)")
        self.relocation = relocation
        # the exact messages a search scores its candidates by
        self.link_conv = (None if relocation is None else
                          HybridBPConv(self.measurement))
        return self

    @classmethod
    def recommended(cls, **overrides) -> 'GaussianBP':
        r"""Gaussian BP in the configuration chosen on validation
        realizations (:obj:`GBP_RECOMMENDED`): at most 20 iterations per
        step, stopping once no belief mean moves by more than 1 cm, and
        covariance inflation :math:`\kappa = 1.5`. Chosen on the paper's
        test network, seed 11, 10 realizations, before any test
        realization was tracked: :math:`\kappa = 1, 1.25, 1.5, 1.75, 2`
        gave :math:`P_\mathrm{out}` (1 m) 0.0100, 0.0067, 0.0073, 0.0088,
        0.0108, P(accept :math:`H_0`) at 0.95 0.793, 0.899, 0.934, 0.942,
        0.945 and RMSE 0.420, 0.396, 0.407, 0.523, 0.538 m (the
        centralized filter that keeps marginals only: 0.0094, 0.809 and
        0.413 m); 1.5 is the smallest inflation that is consistent (at
        least 0.93). The reported covariance's :obj:`report_inflation`
        :math:`\kappa_r = 2.5` (issue 62) was chosen on 10 validation
        realizations (seed 1) of each of the paper's, the NLOS, the sparse,
        the wide-prior and the 3-D networks, the two-sided P(accept 0.95)
        of :math:`\kappa_r = 1, 1.5, 2, 2.5, 3, 4` being 0.900, 0.947,
        0.957, 0.955, 0.954, 0.954 (paper), 0.790, 0.889, 0.929, 0.941,
        0.942, 0.943 (NLOS likelihood), 0.716, 0.810, 0.854, 0.865, 0.866,
        0.865 (sparse), 0.854, 0.920, 0.941, 0.947, 0.950, 0.950 (wide
        prior) and 0.773, 0.888, 0.930, 0.942, 0.942, 0.941 (3-D): the
        bound by the prediction saturates it beyond 2.5, the smallest
        within 0.005 of the best worst network (0.866). It changes no
        estimate. :obj:`overrides` replace or add constructor
        arguments."""
        return cls(**{**GBP_RECOMMENDED, **overrides})

    def predict(self, mean: Tensor, cov: Tensor, anchor: Tensor,
                motion: Optional[MotionModel] = None,
                control: Optional[Tensor] = None,
                point: Optional[Tensor] = None):
        r"""The prediction of every agent's mean :math:`(N, S)` and
        covariance :math:`(N, S, S)` by :obj:`motion` (the tracker's motion
        model by default) with every node's known input :obj:`control`
        :math:`(N, C)`, the transition linearized at the means (or at the
        states :obj:`point` :math:`(N, S)`: :math:`f(\mathbf{p}) +
        \mathbf{F} (\boldsymbol{\mu} - \mathbf{p})`); anchors keep
        theirs."""
        motion = self.motion if motion is None else motion
        agents = ~anchor
        mean, cov = mean.clone(), cov.clone()
        given = inputs(None if control is None else
                       control[agents].to(mean))
        at = mean[agents] if point is None else point[agents].to(mean)
        moved, jacobian, noise = motion.linearize(at, **given)
        cov[agents] = symmetrize(
            jacobian @ cov[agents] @ jacobian.transpose(-1, -2) + noise)
        if point is not None:  # the mean's offset from the point carried
            moved = moved + (jacobian @ (mean[agents] - at).unsqueeze(
                -1)).squeeze(-1)
        mean[agents] = moved
        return mean, cov

    def steps(self, data: Realization,
              generator=None) -> Iterator[StepOutput]:
        r"""Runs the time loop lazily, yielding a
        :class:`~tg_nebp.filters.StepOutput` per time step (without
        particles): :meth:`step` over the realization's links.

        Args:
            data (Realization): A single or batched realization.
            generator (torch.Generator, optional): Used only by a
                measurement model whose linearization draws (a Monte Carlo
                Fisher information); of a list of generators, the first.
                (default: :obj:`None`)
        """
        self.check(data)
        if isinstance(generator, (list, tuple)):
            generator = generator[0] if generator else None
        graph_of = graph_index(data)
        num_graphs = int(graph_of.max()) + 1
        state = self.initial_state(data)
        for t, ((edge_index, edge_attr), control) in enumerate(zip(
                data.edges_by_step(), self.controls_of(data))):
            output, state = self.step(state, edge_index, edge_attr,
                                      data.anchor, t, generator,
                                      graph_of=graph_of,
                                      num_graphs=num_graphs,
                                      control=control)
            yield output

    def initial_state(self, data: Realization,
                      generator=None) -> GaussianState:
        r"""The state before the first step of the nodes of :obj:`data`
        (its :obj:`prior_mean`, :obj:`prior_cov` and :obj:`anchor` are
        read): the prior in float64 (its triangles averaged), every node
        :obj:`fresh` (a given prior: not inflated before its first
        prediction), and the
        :meth:`initial_memory`. A prior whose prediction is singular is
        refused (:func:`~tg_nebp.gaussian.check_predicted_prior`). No
        draws."""
        check_predicted_prior(data, self.motion, 'Gaussian BP',
                              self.use_control)
        anchor = data.anchor
        # symmetric to rounding as validated; carried exactly symmetric
        cov = symmetrize(data.prior_cov.double())
        return GaussianState(data.prior_mean.double(), cov,
                             torch.ones_like(anchor),
                             self.initial_memory(anchor.numel(),
                                                 anchor.device), cov)

    def step(self, state: GaussianState, edge_index: Tensor,
             edge_attr: Tensor, anchor: Tensor, t: int, generator=None,
             motion: Optional[MotionModel] = None,
             graph_of: Optional[Tensor] = None, num_graphs: int = 1,
             control: Optional[Tensor] = None
             ) -> Tuple[StepOutput, GaussianState]:
        r"""One time step (:meth:`solve_step`'s output and state), the
        arithmetic that the offline loop
        (:meth:`steps`), a live session
        (:class:`~tg_nebp.filters.TrackingSession`) and a partitioned run
        share: the last step's beliefs handed on (:meth:`carry`) and
        inflated (:meth:`inflation_of`, no further than the step's
        prediction: :func:`~tg_nebp.gaussian.bounded_inflation`; a
        :obj:`fresh` prior is not), predicted
        by :obj:`motion` (the tracker's by default; a session's time step
        differs per step) with every node's known input :obj:`control`
        :math:`(N, C)`, then the iterations on the links
        :obj:`edge_index` :math:`(2, E)` with features :obj:`edge_attr`
        :math:`(E, F)`, sorted by receiver. Returns the step's
        :class:`~tg_nebp.filters.StepOutput` (time index :obj:`t`) and
        the state after it. :obj:`graph_of` :math:`(N)` gives every
        node's graph of a batch of :obj:`num_graphs` (one graph by
        default)."""
        output, state = self.solve_step(state, edge_index, edge_attr,
                                        anchor, t, generator, motion,
                                        graph_of, num_graphs, control)[:2]
        return self.reported(output, state), state

    def reported(self, output: StepOutput,
                 state: GaussianState) -> StepOutput:
        r"""The step's :obj:`output` as this tracker reports it: its
        covariances inflated by :obj:`report_inflation`, no further than
        the step's prediction (:obj:`state.predicted`); the output itself
        with :obj:`report_inflation` 1."""
        if self.report_inflation == 1:
            return output
        kappa = output.cov.new_full(output.cov.shape[:1],
                                    self.report_inflation)
        return output._replace(cov=bounded_inflation(
            output.cov, state.predicted.to(output.cov), kappa))

    def solve_step(self, state: GaussianState, edge_index: Tensor,
                   edge_attr: Tensor, anchor: Tensor, t: int,
                   generator=None, motion: Optional[MotionModel] = None,
                   graph_of: Optional[Tensor] = None, num_graphs: int = 1,
                   control: Optional[Tensor] = None) -> SolvedStep:
        r""":meth:`step` with what its iterations ended on
        (:class:`~tg_nebp.filters.SolvedStep`: the final beliefs, the
        step's factors and their last messages); the same arguments."""
        mean, cov, memory = state.mean, state.cov, state.memory
        if not bool(state.fresh.all()):
            mean, cov, memory, predicted = self.carry(mean, cov, memory,
                                                      state.predicted)
            # the filter's own beliefs are inflated, not a given prior
            inflated = bounded_inflation(
                cov, predicted, self.inflation_of(cov, memory, anchor))
            cov = torch.where(state.fresh.view(-1, 1, 1), cov, inflated)
        mean, cov = self.predict(mean, cov, anchor, motion, control)
        predicted = cov
        agents = ~anchor
        info = torch.zeros_like(cov)
        info[agents] = _inverse(cov[agents])
        prior = GaussianBelief(mean, info)
        edge_attr = edge_attr.double()
        edge_index = edge_index.long()
        if graph_of is None:
            graph_of = torch.zeros_like(anchor, dtype=torch.long)
        factors = self.conv.factors(edge_index, anchor, mean.size(-1))
        belief, memory, messages = self._iterate_step(
            _Active(torch.arange(anchor.numel(), device=anchor.device),
                    prior, prior, edge_index, edge_attr, anchor, None,
                    factors, memory, graph_of,
                    torch.arange(factors.index.size(1),
                                 device=anchor.device)),
            num_graphs, generator)
        # every step's messages start afresh: wrapping the angles between
        # steps changes nothing but the report
        mean = self.motion.layout(belief.mean.size(-1)).wrap(belief.mean)
        cov = torch.zeros_like(belief.info)
        cov[agents] = _inverse(belief.info[agents])
        solved = SolvedStep(StepOutput(t, mean, cov), GaussianState(
            mean, cov, torch.zeros_like(state.fresh), memory, predicted),
            belief, factors, messages)
        if self.relocation is None:
            return solved
        return relocation_step(self, solved, edge_index, edge_attr, anchor,
                               state.fresh, graph_of, t)

    def link_weights(self, solved: SolvedStep, edge_index: Tensor,
                     edge_attr: Tensor, anchor: Tensor) -> Optional[Tensor]:
        r"""The power :math:`(M)` to which a method that scores the exact
        likelihood of the step's links (the relocation's search, hybrid
        BP's particles) raises each message edge's of :obj:`solved`, so
        that it weighs the links as this tracker's messages do:
        :obj:`None` (the likelihood itself) for Gaussian BP, the inverse
        noise scale of each edge's target with a
        :obj:`noise_adaptation`."""
        if self.noise_adaptation is None or solved.messages is None:
            return None
        return self.noise_adaptation.message_weights(solved.state.memory,
                                                     solved.factors)

    def reinitialized(self, state: GaussianState, nodes: Tensor,
                      mean: Tensor, cov: Tensor) -> GaussianState:
        r"""The :obj:`state` with the beliefs of the :obj:`nodes` (a mask
        :math:`(N)`) replaced by the Gaussians of their rows of
        :obj:`mean` :math:`(N, S)` and :obj:`cov` :math:`(N, S, S)`,
        given as priors (:obj:`fresh`: not inflated before their next
        prediction): what re-initializes a lost agent
        (:class:`~tg_nebp.filters.HybridBP` does where its particles
        contradict the belief). Rows outside the mask are unchanged."""
        rows = nodes.view(-1, 1, 1)
        return state._replace(
            mean=torch.where(nodes.view(-1, 1), mean, state.mean),
            cov=torch.where(rows, cov, state.cov), fresh=state.fresh | nodes,
            predicted=torch.where(rows, cov, state.predicted))

    def initial_memory(self, num_nodes: int,
                       device=None) -> Optional[Tensor]:
        r"""What the iterations carry besides the beliefs, one row per
        node, before the first step: nothing for Gaussian BP (a learned
        correction keeps its node embeddings there), the noise scales'
        sums with a :obj:`noise_adaptation`
        (:meth:`NoiseAdaptation.initial_memory
        <tg_nebp.filters.NoiseAdaptation.initial_memory>`)."""
        if self.noise_adaptation is not None:
            return self.noise_adaptation.initial_memory(num_nodes, device)
        return None

    def inflation_of(self, cov: Tensor, memory: Optional[Tensor],
                     anchor: Tensor) -> Tensor:
        r"""Every node's inflation :math:`\kappa_i` :math:`(N)` of its
        belief covariance :obj:`cov` :math:`(N, S, S)` before the
        prediction of every step after the first: :obj:`inflation`."""
        return cov.new_full(cov.shape[:1], self.inflation)

    def iterate(self, prior: GaussianBelief, belief: GaussianBelief,
                edge_index: Tensor, edge_attr: Tensor, anchor: Tensor,
                messages, generator, factors, memory: Optional[Tensor],
                iteration: int):
        r"""One iteration of the conv: the new beliefs, messages and
        memory (:meth:`initial_memory`). With a :obj:`noise_adaptation`,
        the first iteration (at the predicted beliefs) adds the step's
        links to every agent's noise scale, and every iteration's messages
        are tempered by their targets' scales."""
        adaptation = self.noise_adaptation
        if adaptation is None:
            new, messages = self.conv(prior, belief, edge_index, edge_attr,
                                      anchor, messages, generator, factors,
                                      validate=False)
            return new, messages, memory
        if iteration == 0:
            memory = self.adapted_noise(memory, belief, edge_index,
                                        edge_attr, anchor, generator)
        new = tempered_messages(
            self.conv.step_messages(belief, edge_index, edge_attr, anchor,
                                    factors, messages, generator),
            adaptation.message_weights(memory, factors))
        return (self.conv.beliefs(prior, belief, as_factor_messages(new),
                                  factors, anchor), new, memory)

    def adapted_noise(self, memory: Tensor, belief: GaussianBelief,
                      edge_index: Tensor, edge_attr: Tensor, anchor: Tensor,
                      generator=None) -> Tensor:
        r"""The :obj:`memory` of the :obj:`noise_adaptation` after the
        step's links, at the predicted :obj:`belief`
        (:meth:`NoiseAdaptation.updated
        <tg_nebp.filters.NoiseAdaptation.updated>`)."""
        return self.noise_adaptation.updated(memory, self.measurement,
                                             belief, edge_index, edge_attr,
                                             anchor, generator)

    def carry(self, mean: Tensor, cov: Tensor, memory: Optional[Tensor],
              predicted: Tensor):
        r"""What a step hands to the next (at the start of the next, after
        the step's output was used): the beliefs, the memory and the
        step's prediction, unchanged here."""
        return mean, cov, memory, predicted

    def _iterate_step(self, work: _Active, num_graphs: int, generator
                      ) -> Tuple[GaussianBelief, Optional[Tensor],
                                 Optional[tuple]]:
        # the iterations of one step: the beliefs, memory and messages
        # at the end. A graph whose means all moved by at most the
        # tolerance in an iteration has converged: it keeps that
        # iteration's beliefs and messages, and the iterations go on
        # without it (the graphs share no link), so each graph of a batch
        # gets what it gets alone and batching does not iterate converged
        # graphs
        belief, memory, messages = work.belief, work.memory, None
        for iteration in range(self.num_iterations):
            new, new_messages, new_memory = self.iterate(
                work.prior, work.belief, work.edge_index, work.edge_attr,
                work.anchor, work.messages, generator, work.factors,
                work.memory, iteration)
            step = (new.mean - work.belief.mean).abs().amax(-1)
            work = work._replace(belief=new, messages=new_messages,
                                 memory=new_memory)
            if messages is None:  # the first iteration's: every edge's
                messages = new_messages
            if self.tolerance is None:
                continue
            largest = self.largest_moves(step, work.graph_of, num_graphs)
            # NaN compares false: a diverged graph is not converged
            done = (largest <= self.tolerance)[work.graph_of]
            if bool(done.any()):
                belief, memory, messages = _written(work, belief, memory,
                                                    messages)
                if bool(done.all()):
                    return belief, memory, messages
                work = self._restrict(work, ~done)
        return _written(work, belief, memory, messages)

    def largest_moves(self, step: Tensor, graph_of: Tensor,
                      num_graphs: int) -> Tensor:
        r"""Every graph's largest move of a belief mean in an iteration
        :math:`(G)`, from every node's :obj:`step` (what the tolerance
        stops on)."""
        return step.new_zeros(num_graphs).scatter_reduce(0, graph_of, step,
                                                         'amax')

    def _restrict(self, work: _Active, keep: Tensor) -> _Active:
        # the nodes 'keep' of the graphs that still iterate, with their
        # links, factors, previous messages and memory: renumbered in
        # order, so the factors' message edges keep their order and every
        # node sums its messages as before
        nodes = keep.nonzero().view(-1)
        number = torch.full_like(keep, -1, dtype=torch.long)
        number[nodes] = torch.arange(nodes.numel(), device=nodes.device)
        links = keep[work.edge_index[1]]
        edge_index = number[work.edge_index[:, links]]
        anchor = work.anchor[nodes]
        kept = keep[work.factors.index[1]]
        return _Active(
            work.nodes[nodes],
            GaussianBelief(*(t[nodes] for t in work.prior)),
            GaussianBelief(*(t[nodes] for t in work.belief)), edge_index,
            work.edge_attr[links], anchor,
            type(work.messages)(*(t[kept] for t in work.messages)),
            self.conv.restricted_factors(work.factors, keep,
                                         work.prior.mean.size(-1)),
            None if work.memory is None else work.memory[nodes],
            work.graph_of[nodes], work.message_rows[kept])

    def settings(self) -> dict:
        out = dict(iterations=self.num_iterations,
                   measurement=self.measurement.config(),
                   ends=self.conv.ends, damping=self.conv.damping,
                   tolerance=self.tolerance, inflation=self.inflation,
                   report_inflation=self.report_inflation)
        if self.relocation is not None:
            out['relocation'] = self.relocation.settings()
        if self.noise_adaptation is not None:
            out['noise_adaptation'] = self.noise_adaptation.settings()
        return out

    def __repr__(self) -> str:
        return (f'{self.__class__.__name__}(num_iterations='
                f'{self.num_iterations}, motion={self.motion}, '
                f'measurement={self.measurement}, ends={self.conv.ends!r}, '
                f'damping={self.conv.damping}, tolerance={self.tolerance}, '
                f'inflation={self.inflation}'
                + ('' if self.relocation is None else
                   f', relocation={self.relocation}')
                + ('' if self.noise_adaptation is None else
                   f', noise_adaptation={self.noise_adaptation}') + ')')
