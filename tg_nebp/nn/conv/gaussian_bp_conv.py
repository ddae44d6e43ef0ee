import warnings
from typing import NamedTuple, Optional, Tuple

import torch
from torch import Tensor
from torch_geometric.nn.conv import MessagePassing

from tg_nebp.data.validation import (check_gaussian_belief, check_links,
                                     check_number)
from tg_nebp.models import GaussianRange, MeasurementModel, RangeModel
from tg_nebp.utils import (compute_dtype, link_factors, long_edge_index,
                           symmetrize)

__all__ = ['GaussianBPConv', 'GaussianBelief', 'FactorMessages',
           'RangeMessages', 'Factors', 'Linearization', 'ENDS',
           'position_covariance', 'as_factor_messages', 'tempered_messages',
           'marginal_information']

#: Which ends of a link its range informs: :obj:`"both"` (every measured
#: range is shared with the neighbour it measured) or :obj:`"receiver"`
#: (the paper's convention: an agent uses its own measurements only).
ENDS = ('both', 'receiver')


class GaussianBelief(NamedTuple):
    r"""Gaussian beliefs of the nodes: :obj:`mean` :math:`(N, S)` and
    information (precision) :obj:`info` :math:`(N, S, S)`. An anchor's
    mean is its known state; its information is not used."""
    mean: Tensor
    info: Tensor


class FactorMessages(NamedTuple):
    r"""The factor-to-variable messages of one iteration in information
    form, one per message edge, over the state entries that the
    measurement model reads (:obj:`info` :math:`(M, R, R)`, :obj:`eta`
    :math:`(M, R)`; :math:`R = 2` for a range model's positions), kept for
    the next iteration's extrinsic beliefs."""
    info: Tensor
    eta: Tensor


class RangeMessages(NamedTuple):
    r"""The factor-to-variable messages of range factors in rank-one form
    (:meth:`GaussianBPConv.range_messages`): a range factor's information
    lies along its link's direction, so each message is a scalar
    pseudo-measurement of the target along the unit vector
    :obj:`direction` :math:`\mathbf{u}` :math:`(M, R)` from the target to
    the source, with information :math:`a \mathbf{u} \mathbf{u}^\top`
    (:obj:`weight` :math:`a` :math:`(M)`) and information vector :math:`b
    \mathbf{u}` (:obj:`coefficient` :math:`b` :math:`(M)`)."""
    weight: Tensor
    coefficient: Tensor
    direction: Tensor

    def factor_messages(self) -> FactorMessages:
        r"""The same messages as matrices and vectors
        (:class:`FactorMessages`), exactly symmetric."""
        u = self.direction
        return FactorMessages(
            self.weight.view(-1, 1, 1) * (u.unsqueeze(-1) * u.unsqueeze(-2)),
            self.coefficient.view(-1, 1) * u)


class Linearization(NamedTuple):
    r"""Every factor linearized at the current belief means, as each
    message edge reads it (its target's half second): the factor's
    information :obj:`info` :math:`(M, 2R, 2R)` and vector :obj:`eta`
    :math:`(M, 2R)` on :math:`[\mathbf{x}_s; \mathbf{x}_t]`, and the
    gradient :obj:`grad` :math:`(M, 2R)` of its log-likelihood there
    (:meth:`GaussianBPConv.linearize`)."""
    info: Tensor
    eta: Tensor
    grad: Tensor


class Factors(NamedTuple):
    r"""The factors of one time step's links and their message edges
    (:meth:`GaussianBPConv.factors`), fixed for the step's iterations:
    every factor's two end nodes :obj:`ends` :math:`(P, 2)`; where every
    element of every link's linearization goes in its factor's
    :math:`[\mathbf{x}_a; \mathbf{x}_b]` (:obj:`curvature_slots`
    :math:`(E (2R)^2)`, :obj:`gradient_slots` :math:`(E \cdot 2R)`, flat
    positions: a link from :math:`b` to :math:`a` has its halves swapped);
    the message edges :obj:`index` :math:`(2, M)` (source, target), where
    each reads its factor with its target's half second
    (:obj:`message_slots` :math:`(M (2R)^2)`, :obj:`message_eta_slots`
    :math:`(M \cdot 2R)`) and the message edge of the same factor to the
    other end :obj:`reverse` :math:`(M)` (:math:`-1` if none); the factor
    of every link :obj:`factor` :math:`(E)` and whether it runs from the
    factor's second end to its first (:obj:`swapped`), the factor of every
    message edge :obj:`link` :math:`(M)` and the end it informs
    (:obj:`end`, 0 or 1). The slots are :obj:`None` where the factors
    were made for the rank-one messages of range factors, which do not
    read them."""
    ends: Tensor
    curvature_slots: Optional[Tensor]
    gradient_slots: Optional[Tensor]
    index: Tensor
    message_slots: Optional[Tensor]
    message_eta_slots: Optional[Tensor]
    reverse: Tensor
    factor: Tensor
    swapped: Tensor
    link: Tensor
    end: Tensor


def _halves(width: int, swap: Tensor) -> Tensor:
    # the entries of [x_a; x_b] (2R) in the order [x_b; x_a] where 'swap'
    # (one row per item)
    order = torch.arange(2 * width, device=swap.device)
    return torch.where(swap.view(-1, 1), order.roll(width), order)


def _slots(item: Tensor, swap: Tensor, width: int) -> Tuple[Tensor, Tensor]:
    # flat positions of the (2R, 2R) matrix and 2R vector of 'item', halves
    # swapped where 'swap': one row per link or message edge
    order = _halves(width, swap)  # [n, 2R]
    size = 2 * width
    matrix = (item.view(-1, 1, 1) * size * size + order.view(-1, size, 1) *
              size + order.view(-1, 1, size))
    return matrix.reshape(-1), (item.view(-1, 1) * size + order).reshape(-1)


def _placed(factors: Factors, width: int) -> Factors:
    # the factors with the slots of the general messages, for factors made
    # for the rank-one ones
    curvature, gradient = _slots(factors.factor, factors.swapped, width)
    message, message_eta = _slots(factors.link, factors.end == 0, width)
    return factors._replace(curvature_slots=curvature,
                            gradient_slots=gradient, message_slots=message,
                            message_eta_slots=message_eta)


def _dot(a: Tensor, b: Tensor) -> Tensor:
    # the dot products of vectors given by components (R, M), summed over
    # the few components one by one (a reduction over a short dimension is
    # many times slower)
    out = a[0] * b[0]
    for k in range(1, a.size(0)):
        out = out + a[k] * b[k]
    return out


def _matvec(matrices: Tensor, vectors: Tensor) -> Tensor:
    # the products of many small matrices (R, R, M) and vectors (R, M), by
    # components as _dot
    out = matrices[:, 0] * vectors[0]
    for k in range(1, vectors.size(0)):
        out = out + matrices[:, k] * vectors[k]
    return out


def _inverse(matrices: Tensor) -> Tensor:
    # the inverses of many small matrices (B, R, R): 2 x 2 in closed form
    # (several times faster than a batched solve of that size), larger ones
    # by torch.linalg.inv
    if matrices.size(-1) != 2:
        return torch.linalg.inv(matrices)
    a, b = matrices[:, 0, 0], matrices[:, 0, 1]
    c, d = matrices[:, 1, 0], matrices[:, 1, 1]
    adjugate = torch.stack([d, -b, -c, a], -1).view(-1, 2, 2)
    return adjugate / (a * d - b * c).view(-1, 1, 1)


def marginal_information(info: Tensor, mean: Tensor, width: int,
                         anchor: Tensor) -> Tuple[Tensor, Tensor]:
    r"""Every agent's Gaussian belief (information :obj:`info`
    :math:`(N, S, S)`, :obj:`mean` :math:`(N, S)`) marginalized onto its
    first :obj:`width` entries :math:`R` (a factor's scope), in
    information form (the Schur complement of the other entries): the
    information matrices :math:`(N, R, R)` and vectors :math:`(N, R)`.
    Anchors (known, no belief to marginalize; mask :obj:`anchor`) get an
    identity and zeros, which no message reads."""
    eta = (info @ mean.unsqueeze(-1)).squeeze(-1)
    info_rr, eta_r = info[:, :width, :width], eta[:, :width]
    if width < mean.size(-1):
        info_ro, info_oo = info[:, :width, width:], info[:, width:, width:]
        eye = torch.eye(info_oo.size(-1), dtype=info.dtype,
                        device=info.device)
        gain = info_ro @ _inverse(torch.where(anchor.view(-1, 1, 1), eye,
                                              info_oo))
        info_rr = info_rr - gain @ info_ro.transpose(-1, -2)
        eta_r = eta_r - (gain @ eta[:, width:].unsqueeze(-1)).squeeze(-1)
    eye = torch.eye(width, dtype=info.dtype, device=info.device)
    info_rr = torch.where(anchor.view(-1, 1, 1), eye,
                          symmetrize(info_rr))
    return info_rr, eta_r.masked_fill(anchor.view(-1, 1), 0.0)


def _prior_where_singular(prior: GaussianBelief, mean: Tensor, info: Tensor,
                          singular: Tensor, anchor: Tensor
                          ) -> Tuple[Tensor, Tensor]:
    # the beliefs of the nodes whose information is singular replaced by
    # their priors (a singular prior too: nothing determines the state)
    _, bad_prior = torch.linalg.inv_ex(prior.info)
    lost = singular & bad_prior.bool() & ~anchor
    if bool(lost.any()):
        node = int(lost.nonzero()[0, 0])
        raise ValueError(f"the belief of node {node} has singular "
                         f"information: its prior and messages leave a state "
                         f"entry undetermined")
    nodes = singular.nonzero().view(-1).tolist()
    warnings.warn(f"the belief of node(s) {nodes} became singular (their "
                  f"messages cancel their prior's information): they keep "
                  f"their prior for this step", RuntimeWarning, stacklevel=4)
    keep = singular.view(-1, 1, 1)
    return (torch.where(keep.view(-1, 1), prior.mean, mean),
            torch.where(keep, prior.info, info))


def position_covariance(belief: GaussianBelief, width: int,
                        anchor: Tensor) -> Tensor:
    r"""Every node's covariance on its first :obj:`width` state entries
    :math:`(N, R, R)` (the factors' scope), from its information; zero for
    anchors (known)."""
    eye = torch.eye(belief.info.size(-1), dtype=belief.info.dtype,
                    device=belief.info.device)
    cov, singular = torch.linalg.inv_ex(torch.where(anchor.view(-1, 1, 1),
                                                    eye, belief.info))
    if bool(singular.any()):
        node = int(singular.nonzero()[0, 0])
        raise ValueError(f"the belief of node {node} has singular "
                         f"information: its prior and messages leave a "
                         f"state entry undetermined")
    cov = cov[:, :width, :width]
    cov = symmetrize(cov)
    return cov.masked_fill(anchor.view(-1, 1, 1), 0.0)


def tempered_messages(messages, weight: Tensor):
    r"""The :obj:`messages` (:class:`RangeMessages` or
    :class:`FactorMessages`) with their information and information vector
    scaled by :obj:`weight` :math:`(M)`, their means unchanged: each a
    Gaussian whose variance is :math:`1 / w` times its own."""
    if isinstance(messages, RangeMessages):
        return RangeMessages(messages.weight * weight,
                             messages.coefficient * weight,
                             messages.direction)
    return FactorMessages(messages.info * weight.view(-1, 1, 1),
                          messages.eta * weight.view(-1, 1))


def as_factor_messages(messages) -> 'FactorMessages':
    r""":obj:`messages` as :class:`FactorMessages` (rank-one
    :class:`RangeMessages` expanded)."""
    if isinstance(messages, RangeMessages):
        return messages.factor_messages()
    return messages


def _check_messages(messages, count: int, width: int) -> None:
    # the previous iteration's messages, one per message edge of the
    # factors: a message of another graph would be read at wrong slots
    if isinstance(messages, FactorMessages):
        shapes = (('info', (count, width, width)), ('eta', (count, width)))
    elif isinstance(messages, RangeMessages):
        shapes = (('weight', (count,)), ('coefficient', (count,)),
                  ('direction', (count, width)))
    else:
        raise TypeError(f"'messages' must be FactorMessages or "
                        f"RangeMessages, got {type(messages).__name__}")
    for field, shape in shapes:
        value = getattr(messages, field)
        if not isinstance(value, Tensor) or value.shape != shape:
            raise ValueError(f"'messages.{field}' must have shape "
                             f"{list(shape)} (one per message edge), got "
                             f"{list(getattr(value, 'shape', []))}")
        # (a trailing axis keeps the flattening defined without messages)
        bad = ~torch.isfinite(value.unsqueeze(-1)).flatten(1).all(-1)
        if bool(bad.any()):
            raise ValueError(f"'messages.{field}[{int(bad.nonzero()[0, 0])}]"
                             f"' holds a non-finite value")


class GaussianBPConv(MessagePassing):
    r"""One iteration of Gaussian belief propagation on the range factor
    graph of cooperative localization: every measured link :math:`z_{j \to
    i}` is a factor :math:`p(z_{j \to i} | \mathbf{x}_j, \mathbf{x}_i)`
    between the states of its two ends, linearized at the current belief
    means (as in the Robot Web of `"Distributed Simultaneous Localisation
    and Mapping for Mobile Robots with Gaussian Belief Propagation"
    <https://arxiv.org/abs/2202.03314>`_, Murai, Ortiz, Saeedi, Kelly and
    Davison, IEEE T-RO 2024, and sigma-point / posterior-linearization BP
    for localization), that sends a Gaussian message in information form to
    **both** ends.

    The measurement model linearizes the factor at the means
    :math:`\bar{\mathbf{x}} = [\bar{\mathbf{x}}_j; \bar{\mathbf{x}}_i]`
    (:meth:`~tg_nebp.models.MeasurementModel.linearize`: the gradient
    :math:`\mathbf{g}` of its own log-likelihood and a positive
    semi-definite curvature :math:`\mathbf{W}`, with robust weights for
    non-Gaussian range likelihoods), which makes the factor
    :math:`\boldsymbol{\Lambda}_f = \mathbf{W}`, :math:`\boldsymbol{\eta}_f
    = \mathbf{W} \bar{\mathbf{x}} + \mathbf{g}` on the stacked states. The
    message to end :math:`t` marginalizes the other end :math:`s` against
    its **extrinsic** belief, its belief without this factor's previous
    message to it, :math:`(\boldsymbol{\Lambda}_s -
    \boldsymbol{\Lambda}_{f \to s}, \boldsymbol{\eta}_s -
    \boldsymbol{\eta}_{f \to s})`:

    .. math::
        \boldsymbol{\Lambda}_{f \to t} &= \boldsymbol{\Lambda}_{f,tt} -
        \boldsymbol{\Lambda}_{f,ts} \mathbf{A}^{-1}
        \boldsymbol{\Lambda}_{f,st}, \quad \mathbf{A} =
        \boldsymbol{\Lambda}_{f,ss} + \boldsymbol{\Lambda}_s -
        \boldsymbol{\Lambda}_{f \to s}

        \boldsymbol{\eta}_{f \to t} &= \boldsymbol{\eta}_{f,t} -
        \boldsymbol{\Lambda}_{f,ts} \mathbf{A}^{-1} \big(
        \boldsymbol{\eta}_{f,s} + \boldsymbol{\eta}_s -
        \boldsymbol{\eta}_{f \to s}\big),

    so a belief never receives its own information back and iterations do
    not count a measurement twice. An anchor end is known: its factor
    conditions on it (:math:`\boldsymbol{\Lambda}_{f \to t} =
    \boldsymbol{\Lambda}_{f,tt}`). Every node adds its incoming messages to
    its (predicted) prior,

    .. math::
        \boldsymbol{\Lambda}_i = \boldsymbol{\Lambda}_i^- + \sum_f
        \boldsymbol{\Lambda}_{f \to i}, \quad \boldsymbol{\eta}_i =
        \boldsymbol{\eta}_i^- + \sum_f \boldsymbol{\eta}_{f \to i}.

    A factor and its messages live on the state entries that the
    likelihood reads (:meth:`~tg_nebp.models.MeasurementModel.scope`: a
    range model's positions), and a source's extrinsic belief enters
    marginalized onto them. With :obj:`ends="both"` the two ranges of a
    pair of nodes are one factor
    (:meth:`~tg_nebp.nn.conv.GaussianBPConv.factors`). In PyG terms the
    message to :math:`j` runs on the flipped edge :math:`i \to j` with the
    same link features; the sum is :obj:`aggr="add"`. Memory is
    :math:`O(|\mathcal{E}| S^2)`, and nothing depends on a particle
    count.

    Args:
        measurement (MeasurementModel, optional): The measurement model.
            (default: :obj:`GaussianRange()`)
        ends (str, optional): :obj:`"both"`: every range informs both ends
            of its link (links are measured in both directions with
            independent noise, so each direction is its own factor);
            :obj:`"receiver"`: only the agent that measured it, the paper's
            convention. (default: :obj:`"both"`)
        damping (float, optional): Weight :math:`\beta \in [0, 1)` of the
            previous message in each new one, :math:`(1 - \beta)
            \mathbf{m}_\mathrm{new} + \beta \mathbf{m}_\mathrm{old}` in
            information form. (default: :obj:`0.0`)
        compile (bool, optional): Compute the rank-one messages
            (:meth:`range_messages`) with a :func:`torch.compile`-fused
            kernel (the first calls compile; the same arithmetic, equal to
            rounding). (default: :obj:`False`)

    Shapes:
        - **input:**
          prior and beliefs: means :math:`(|\mathcal{V}|, S)`, information
          :math:`(|\mathcal{V}|, S, S)`,
          edge indices :math:`(2, |\mathcal{E}|)`,
          link features :math:`(|\mathcal{E}|, F)` (the range first),
          anchor mask :math:`(|\mathcal{V}|)`,
          previous messages :math:`(M, R, R)`, :math:`(M, R)`, or for a
          range model (:attr:`rank_one`) :math:`(M)`, :math:`(M)`,
          :math:`(M, R)` *(optional)*
        - **output:** beliefs, means :math:`(|\mathcal{V}|, S)` and
          information :math:`(|\mathcal{V}|, S, S)`, and the messages
          (:class:`~tg_nebp.nn.conv.FactorMessages`, or
          :class:`~tg_nebp.nn.conv.RangeMessages` for a range model)
    """
    def __init__(self, measurement: Optional[MeasurementModel] = None,
                 ends: str = 'both', damping: float = 0.0,
                 compile: bool = False):
        super().__init__(aggr='add', node_dim=0)
        self.measurement = measurement or GaussianRange()
        if not isinstance(self.measurement, MeasurementModel):
            raise TypeError(f"'measurement' must be a MeasurementModel, got "
                            f"{self.measurement!r}")
        if ends not in ENDS:
            raise ValueError(f"'ends' must be one of {list(ENDS)}, got "
                             f"{ends!r}")
        damping = check_number(damping, 'damping', inclusive=True)
        if damping >= 1:
            raise ValueError(f"'damping' must lie in [0, 1), got {damping}")
        self.ends = ends
        self.damping = damping
        self.compile = bool(compile)
        # the pointwise arithmetic of many message edges and its gathers
        # fuse into a few loops (the sums into the beliefs stay outside)
        self._range_messages = torch.compile(
            self.range_messages, dynamic=True) if compile else \
            self.range_messages

    def factors(self, edge_index: Tensor, anchor: Tensor, state_dim: int,
                slots: Optional[bool] = None) -> Factors:
        r"""The factors of the links :obj:`edge_index` :math:`(2, E)` and
        the message edges that carry their messages, for states of size
        :obj:`state_dim` (:class:`~tg_nebp.nn.conv.Factors`): what the
        iterations of a time step share. The factor graph is
        :func:`~tg_nebp.utils.link_factors`'s: with :obj:`ends="both"` the
        two measurements of a pair of nodes (independent noise) form one
        factor on :math:`[\mathbf{x}_a; \mathbf{x}_b]`, :math:`a < b`,
        that informs both; with :obj:`ends="receiver"` every measurement
        is its own factor, whose one message goes to the agent that
        measured it. :obj:`slots`: whether to place the matrices of the
        general messages (by default, unless :attr:`rank_one`)."""
        graph = link_factors(edge_index, anchor, self.ends)
        width = len(self.measurement.scope(state_dim))
        factors = Factors(graph.ends, None, None, graph.index, None, None,
                          graph.reverse, graph.factor, graph.swapped,
                          graph.link, graph.end)
        if slots or (slots is None and not self.rank_one):
            return _placed(factors, width)
        return factors

    def restricted_factors(self, factors: Factors, keep: Tensor,
                           state_dim: int) -> Factors:
        r"""The :obj:`factors` of the nodes :obj:`keep` (a bool mask) and
        of their links, the nodes renumbered in order: what
        :meth:`factors` gives for the kept links, without sorting them
        again (the time loop's graphs that still iterate). Every link of a
        kept node must have both ends kept (whole graphs of a batch)."""
        number = torch.cumsum(keep, 0) - 1
        subset, _, _ = self.factor_subset(factors, keep[factors.ends[:, 1]],
                                          state_dim)
        return subset._replace(ends=number[subset.ends],
                               index=number[subset.index])

    def factor_subset(self, factors: Factors, chosen: Tensor,
                      state_dim: int) -> Tuple[Factors, Tensor, Tensor]:
        r"""The factors :obj:`chosen` :math:`(P)` (a bool mask) of
        :obj:`factors`, with their links and message edges in their order
        and the nodes' numbers unchanged: what :meth:`factors` gives for
        the kept links, without sorting them again (the factors whose
        messages a residual schedule recomputes). Returns the
        :class:`~tg_nebp.nn.conv.Factors` and the masks of the links
        :math:`(E)` and message edges :math:`(M)` kept."""
        factor_number = torch.cumsum(chosen, 0) - 1
        kept_link = chosen[factors.factor]
        kept_message = chosen[factors.link]
        message_number = torch.cumsum(kept_message, 0) - 1
        reverse = factors.reverse[kept_message]
        reverse = torch.where(reverse >= 0,
                              message_number[reverse.clamp_min(0)], reverse)
        subset = Factors(
            factors.ends[chosen], None, None,
            factors.index[:, kept_message], None, None, reverse,
            factor_number[factors.factor[kept_link]],
            factors.swapped[kept_link],
            factor_number[factors.link[kept_message]],
            factors.end[kept_message])
        if factors.curvature_slots is not None:
            subset = _placed(subset, len(self.measurement.scope(state_dim)))
        return subset, kept_link, kept_message

    @property
    def rank_one(self) -> bool:
        r"""Whether :meth:`forward` sends rank-one messages
        (:meth:`range_messages`): the measurement model is a
        :class:`~tg_nebp.models.RangeModel` that linearizes as every
        range model does (its factors lie along their links) and there is
        no damping (which would mix two directions)."""
        return (isinstance(self.measurement, RangeModel) and
                type(self.measurement).linearize is RangeModel.linearize and
                self.damping == 0)

    def forward(self, prior: GaussianBelief, belief: GaussianBelief,
                edge_index: Tensor, edge_attr: Tensor, anchor: Tensor,
                messages=None,
                generator: Optional[torch.Generator] = None,
                factors: Optional[Factors] = None, validate: bool = True
                ) -> Tuple[GaussianBelief, tuple]:
        r"""Runs one iteration: the new beliefs and messages
        (:class:`~tg_nebp.nn.conv.RangeMessages` for a range model,
        :attr:`rank_one`, unless given the general
        :class:`~tg_nebp.nn.conv.FactorMessages`).

        Args:
            prior (GaussianBelief): The nodes' (predicted) prior.
            belief (GaussianBelief): The current beliefs: their means are
                the linearization points, and with :obj:`messages` they
                give the extrinsic beliefs.
            edge_index (torch.Tensor): Links :math:`j \to i` (agent
                :math:`i` measured node :math:`j`).
            edge_attr (torch.Tensor): Link features, the range first.
            anchor (torch.Tensor): Bool mask of anchors (known states).
            messages (FactorMessages or RangeMessages, optional): The
                previous iteration's messages on the message edges of
                :meth:`factors` (none at the first). (default: :obj:`None`)
            generator (torch.Generator, optional): For a measurement model
                whose linearization draws (a Monte Carlo Fisher
                information). (default: :obj:`None`)
            factors (Factors, optional): :meth:`factors` of the links, which
                the iterations of a time step share (computed if
                :obj:`None`). (default: :obj:`None`)
            validate (bool, optional): Check the inputs as
                :class:`~tg_nebp.nn.conv.ParticleBPConv` does (the links,
                the ranges, the anchor mask; the beliefs finite, symmetric
                and positive semi-definite; the messages' shapes).
                Trackers check their data once and pass :obj:`False`.
                (default: :obj:`True`)

        Half precision is computed in float32 (information matrices
        overflow it): the outputs have the promoted dtype of the inputs and
        float32.
        """
        prior, belief, edge_index, edge_attr, messages, factors = (
            self.prepare(prior, belief, edge_index, edge_attr, anchor,
                         messages, factors, validate))
        new = self.step_messages(belief, edge_index, edge_attr, anchor,
                                 factors, messages, generator)
        return self.beliefs(prior, belief, as_factor_messages(new), factors,
                            anchor), new

    def step_messages(self, belief: GaussianBelief, edge_index: Tensor,
                      edge_attr: Tensor, anchor: Tensor, factors: Factors,
                      messages=None,
                      generator: Optional[torch.Generator] = None,
                      fresh: Optional[Tensor] = None):
        r"""The messages of one iteration from the current beliefs and
        the previous :obj:`messages` (the first half of :meth:`forward`):
        rank-one (:meth:`range_messages`) for a range model
        (:attr:`rank_one`) unless given general ones, else
        :meth:`messages` of the :meth:`linearize` d factors. The message
        edges of the mask :obj:`fresh` :math:`(M)` have no previous message
        (their entries of :obj:`messages` are zero): they are not damped,
        as none is at the first iteration. Inputs as :meth:`prepare` gives
        them."""
        if self.rank_one and not isinstance(messages, FactorMessages):
            return self._range_messages(belief, edge_index, edge_attr,
                                        anchor, factors, messages)
        if isinstance(messages, RangeMessages):
            messages = messages.factor_messages()
        linearization = self.linearize(belief, edge_index, edge_attr,
                                       factors, generator)
        return self.messages(belief, anchor, factors, linearization,
                             messages, fresh)

    def prepare(self, prior: GaussianBelief, belief: GaussianBelief,
                edge_index: Tensor, edge_attr: Tensor, anchor: Tensor,
                messages: Optional[FactorMessages] = None,
                factors: Optional[Factors] = None, validate: bool = True):
        r"""The inputs of :meth:`forward` checked (with :obj:`validate`)
        and in the compute dtype, with the :obj:`factors` of the links
        (computed if :obj:`None`): :obj:`(prior, belief, edge_index,
        edge_attr, messages, factors)`."""
        if validate:
            check_gaussian_belief(*prior, 'prior')
            check_gaussian_belief(*belief, 'belief', prior.mean.size(0))
            if belief.mean.shape != prior.mean.shape:
                raise ValueError(f"'belief.mean' {list(belief.mean.shape)} "
                                 f"and 'prior.mean' "
                                 f"{list(prior.mean.shape)} differ in shape")
            check_links(edge_index, edge_attr, self.measurement.features,
                        prior.mean.size(0), anchor,
                        self.measurement.negative_ranges)
        dtype = compute_dtype(*prior, *belief, edge_attr)
        prior = GaussianBelief(*(t.to(dtype) for t in prior))
        belief = GaussianBelief(*(t.to(dtype) for t in belief))
        edge_attr = edge_attr.to(dtype)
        num_nodes, size = belief.mean.shape
        edge_index = long_edge_index(edge_index, num_nodes)
        if factors is None:
            factors = self.factors(edge_index, anchor, size)
        scope = self.measurement.scope(size)
        width = len(scope)
        if validate and messages is not None:
            _check_messages(messages, factors.index.size(1), width)
        if messages is not None:
            kind = (RangeMessages if isinstance(messages, RangeMessages) else
                    FactorMessages)
            messages = kind(*(t.to(dtype) for t in messages))
        # the scope is a slice of every state: the leading entries (a range
        # model's positions, or the whole state)
        if tuple(scope) != tuple(range(width)):
            raise ValueError(f"Gaussian BP needs a measurement model that "
                             f"reads the leading state entries, but "
                             f"{self.measurement} reads {tuple(scope)}")
        return prior, belief, edge_index, edge_attr, messages, factors

    def linearize(self, belief: GaussianBelief, edge_index: Tensor,
                  edge_attr: Tensor, factors: Factors,
                  generator: Optional[torch.Generator] = None
                  ) -> Linearization:
        r"""Every factor linearized at the belief means, as each message
        edge reads it (:class:`~tg_nebp.nn.conv.Linearization`): the
        measurement model's :meth:`MeasurementModel.linearize
        <tg_nebp.models.MeasurementModel.linearize>` of every link, the two
        ranges of a pair summed into one factor. Inputs as :meth:`prepare`
        gives them (checked, in the compute dtype)."""
        width = len(self.measurement.scope(belief.mean.size(-1)))
        if factors.curvature_slots is None:
            factors = _placed(factors, width)
        src, dst = edge_index
        grad, curvature = self.measurement.linearize(
            edge_attr, belief.mean[src], belief.mean[dst], generator)
        # the factors on [x_a; x_b]: every link's linearization added at
        # its slots (the two ranges of a pair into one factor)
        count = factors.ends.size(0)
        factor_info = curvature.new_zeros(count * 4 * width * width)
        factor_info.index_add_(0, factors.curvature_slots,
                               curvature.reshape(-1))
        factor_grad = grad.new_zeros(count * 2 * width)
        factor_grad.index_add_(0, factors.gradient_slots, grad.reshape(-1))
        point = belief.mean[:, :width][factors.ends].reshape(count,
                                                             2 * width)
        factor_eta = (factor_info.view(count, 2 * width, 2 * width) @
                      point.unsqueeze(-1)).squeeze(-1) + factor_grad.view(
                          count, 2 * width)
        return Linearization(
            factor_info[factors.message_slots].view(-1, 2 * width,
                                                    2 * width),
            factor_eta.view(-1)[factors.message_eta_slots].view(
                -1, 2 * width),
            factor_grad[factors.message_eta_slots].view(-1, 2 * width))

    def range_messages(self, belief: GaussianBelief, edge_index: Tensor,
                       edge_attr: Tensor, anchor: Tensor, factors: Factors,
                       messages: Optional[RangeMessages] = None
                       ) -> RangeMessages:
        r"""The messages of one iteration in rank-one form
        (:class:`~tg_nebp.nn.conv.RangeMessages`), for a range model
        (:attr:`rank_one`): the same messages as :meth:`messages` sends, in
        closed form. The factor of a pair is :math:`W \nabla d \, \nabla
        d^\top` and its gradient :math:`S \nabla d`, :math:`\nabla d =
        [\mathbf{u}; -\mathbf{u}]` (:math:`W`, :math:`S` the sums of its
        links' robust weights and scores from
        :meth:`~tg_nebp.models.RangeModel.range_linearization`), so the
        Schur complement that marginalizes the source collapses by the
        Sherman-Morrison formula to

        .. math::
            a = \frac{W}{1 + W \sigma}, \quad b = \frac{W m - W
            \bar{d} - S}{1 + W \sigma},

        with :math:`\bar{d} = \mathbf{u}^\top (\bar{\mathbf{p}}_s -
        \bar{\mathbf{p}}_t)` and the source's extrinsic variance
        :math:`\sigma` and mean :math:`m` along :math:`\mathbf{u}` (zero
        and :math:`\mathbf{u}^\top \mathbf{p}_s` for an anchor). The
        extrinsic belief removes the factor's previous rank-one message
        :math:`(a', b', \mathbf{u}')` to the source from its covariance
        :math:`\boldsymbol{\Sigma}_s` and mean :math:`\boldsymbol{\mu}_s`
        by Sherman-Morrison again: with :math:`\tau = \mathbf{u}'^\top
        \boldsymbol{\Sigma}_s \mathbf{u}'` and :math:`\kappa =
        \mathbf{u}^\top \boldsymbol{\Sigma}_s \mathbf{u}'`,
        :math:`\sigma = \mathbf{u}^\top \boldsymbol{\Sigma}_s \mathbf{u}
        + a' \kappa^2 / (1 - a' \tau)` and :math:`m = \mathbf{u}^\top
        \boldsymbol{\mu}_s + \kappa (a' \mathbf{u}'^\top
        \boldsymbol{\mu}_s - b') / (1 - a' \tau)`. Every quantity is a
        scalar of a message edge: no matrix of a link is formed. Inputs as
        :meth:`prepare` gives them."""
        width = len(self.measurement.scope(belief.mean.size(-1)))
        src, dst = edge_index
        unit, score, weight = self.measurement.range_linearization(
            edge_attr, belief.mean.index_select(0, src),
            belief.mean.index_select(0, dst))
        count = factors.ends.size(0)
        # vectors by components (R, M), each a contiguous row, so that the
        # few-term sums below are whole-row operations.
        # A factor's direction, from its second end to its first, from its
        # first link (a link from b to a points the other way; both links of
        # a pair give it exactly: the same difference, negated)
        links = torch.arange(src.numel(), device=src.device)
        first = torch.full((count, ), src.numel(), dtype=torch.long,
                           device=src.device).scatter_reduce_(
                               0, factors.factor, links, 'amin')
        direction = torch.where(factors.swapped, -unit.t(), unit.t())[
            :, first]
        total_weight = weight.new_zeros(count).index_add_(0, factors.factor,
                                                          weight)
        total_score = score.new_zeros(count).index_add_(0, factors.factor,
                                                        score)
        source, target = factors.index
        # from the target to the source: the factor's direction for a
        # message to its second end
        toward = direction.index_select(1, factors.link)
        toward = torch.where(factors.end == 1, toward, -toward)
        information = total_weight.index_select(0, factors.link)
        position = belief.mean[:, :width].t()
        at_source = position.index_select(1, source)
        shift = information * _dot(toward, at_source - position.index_select(
            1, target)) + total_score.index_select(0, factors.link)
        cov = position_covariance(belief, width, anchor).permute(
            1, 2, 0).reshape(width * width, -1).index_select(1, source).view(
                width, width, -1)
        along = _matvec(cov, toward)
        variance = _dot(toward, along)
        mean = _dot(toward, at_source)
        if messages is not None:
            has_old = factors.reverse >= 0
            back = factors.reverse.clamp_min(0)
            old_weight = torch.where(has_old, messages.weight.index_select(
                0, back), 0.0)
            old_coefficient = torch.where(
                has_old, messages.coefficient.index_select(0, back), 0.0)
            old = messages.direction.t().index_select(1, back)
            cross = _dot(old, along)
            remaining = 1 - old_weight * _dot(old, _matvec(cov, old))
            variance = variance + old_weight * cross * cross / remaining
            mean = mean + cross * (old_weight * _dot(old, at_source) -
                                   old_coefficient) / remaining
        scale = 1 / (1 + information * variance)
        return RangeMessages(information * scale,
                             (information * mean - shift) * scale, toward.t())

    def messages(self, belief: GaussianBelief, anchor: Tensor,
                 factors: Factors, linearization: Linearization,
                 messages: Optional[FactorMessages] = None,
                 fresh: Optional[Tensor] = None) -> FactorMessages:
        r"""The factor-to-variable messages of one iteration from the
        factors' :obj:`linearization` (:meth:`linearize`) and the sources'
        extrinsic beliefs (without the previous :obj:`messages`), damped
        as configured (but for the message edges :obj:`fresh`, which have
        no previous message)."""
        width = linearization.grad.size(-1) // 2
        marginal_info, marginal_eta = marginal_information(
            belief.info, belief.mean, width, anchor)
        new = self.edge_updater(
            factors.index, info=marginal_info, eta=marginal_eta,
            point=belief.mean[:, :width], known=anchor,
            factor_info=linearization.info, factor_eta=linearization.eta,
            reverse=factors.reverse, messages=messages)
        if self.damping > 0 and messages is not None:
            damped = FactorMessages(*(
                torch.lerp(n, o, self.damping) for n, o in zip(new,
                                                               messages)))
            if fresh is None:
                return damped
            new = FactorMessages(*(
                torch.where(fresh.view((-1, ) + (1, ) * (n.dim() - 1)), n, d)
                for n, d in zip(new, damped)))
        return new

    def beliefs(self, prior: GaussianBelief, belief: GaussianBelief,
                messages: FactorMessages, factors: Factors,
                anchor: Tensor) -> GaussianBelief:
        r"""The beliefs of the nodes: every agent's :obj:`prior` plus its
        incoming :obj:`messages` (on the message edges of
        :obj:`factors`), solved for the mean; anchors keep
        :obj:`belief`'s known states. An agent whose messages leave its
        information singular (they cancel what its prior knows, as
        rounding does to messages that outweigh a very wide prior by many
        orders) keeps its prior for the step, with a warning that names
        it, and the step goes on; one whose prior alone is singular too is
        a :class:`ValueError` (nothing determines its state)."""
        return self.updated(prior, belief.mean, self.message_sums(
            messages, factors, belief.mean.size(0)), anchor)

    def message_sums(self, messages: FactorMessages, factors: Factors,
                     num_nodes: int) -> Tensor:
        r"""Every node's sum of its incoming :obj:`messages` (on the
        message edges of :obj:`factors`), information and vector
        flattened together :math:`(N, R^2 + R)`."""
        return self.propagate(factors.index, info=messages.info,
                              eta=messages.eta, size=(num_nodes, num_nodes))

    def updated(self, prior: GaussianBelief, known: Tensor, sums: Tensor,
                anchor: Tensor) -> GaussianBelief:
        r"""The beliefs of the nodes from their :obj:`prior` and the
        :meth:`message_sums` :obj:`sums` (the second half of
        :meth:`beliefs`); anchors keep the states :obj:`known`."""
        size = prior.mean.size(-1)
        width = len(self.measurement.scope(size))
        info = prior.info.clone()
        info[:, :width, :width] += sums[:, :width * width].view(
            -1, width, width)
        # a copy, not the squeezed view: adding a message that carries a
        # gradient in place into a view of a grad-free product covering
        # its whole base (a scope of the whole state) is refused by autograd
        total = (prior.info @ prior.mean.unsqueeze(-1)).squeeze(-1).clone()
        total[:, :width] += sums[:, width * width:]
        # anchors keep their known state (an identity keeps the solve
        # finite)
        eye = torch.eye(size, dtype=info.dtype, device=info.device)
        solved, singular = torch.linalg.solve_ex(
            torch.where(anchor.view(-1, 1, 1), eye, info),
            total.unsqueeze(-1))
        mean = solved.squeeze(-1)
        if bool(singular.any()):
            mean, info = _prior_where_singular(prior, mean, info,
                                               singular.bool(), anchor)
        mean = torch.where(anchor.view(-1, 1), known, mean)
        return GaussianBelief(mean, info)

    def edge_update(self, info_j: Tensor, eta_j: Tensor, point_j: Tensor,
                    known_j: Tensor, factor_info: Tensor,
                    factor_eta: Tensor, reverse: Tensor,
                    messages: Optional[FactorMessages]) -> FactorMessages:
        # the message to the target t of every message edge s -> t (its
        # factor's second half), on the factor's scope: the source's
        # extrinsic belief there (its marginal information without this
        # factor's previous message) and the Schur complement that
        # marginalizes the source; an anchor source is conditioned on
        width = point_j.size(-1)
        tt = factor_info[:, width:, width:]
        ts = factor_info[:, width:, :width]
        ss = factor_info[:, :width, :width]
        eta_t, eta_s = factor_eta[:, width:], factor_eta[:, :width]
        ext_info, ext_eta = info_j, eta_j
        if messages is not None:
            has_old = (reverse >= 0).to(info_j.dtype)
            back = reverse.clamp_min(0)
            ext_info = info_j - messages.info[back] * has_old.view(-1, 1, 1)
            ext_eta = eta_j - messages.eta[back] * has_old.view(-1, 1)
        gain = ts @ _inverse(ss + ext_info)
        agent = ~known_j
        info = torch.where(agent.view(-1, 1, 1),
                           tt - gain @ ts.transpose(-1, -2), tt)
        info = symmetrize(info)
        source = torch.where(agent.view(-1, 1), eta_s + ext_eta, point_j)
        eta = eta_t - ((torch.where(agent.view(-1, 1, 1), gain, ts) @
                        source.unsqueeze(-1)).squeeze(-1))
        return FactorMessages(info, eta)

    def message(self, info: Tensor, eta: Tensor) -> Tensor:
        # flattened, so one 'add' aggregation sums information and eta
        return torch.cat([info.flatten(1), eta], -1)

    def __repr__(self) -> str:
        return (f'{self.__class__.__name__}({self.measurement}, '
                f'ends={self.ends!r}, damping={self.damping}'
                + (', compile=True)' if self.compile else ')'))
