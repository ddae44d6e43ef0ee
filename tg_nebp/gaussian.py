r"""Dense joint Gaussians over the agents of one graph, shared by the
centralized filter (:class:`~tg_nebp.filters.CentralizedIEKF`) and the
posterior Cramér-Rao bound (:class:`~tg_nebp.bounds.PosteriorCRB`): where
each graph's agents sit in its joint, the prediction of a joint covariance
through a per-agent motion model, the information of measured links added
into a joint information matrix, the agents' marginals, and the memory
check that refuses a joint too large for the machine before any work
starts. Neither the bound nor a tracker imports the other: what they share
lives here and in the checks of :mod:`tg_nebp.data`.

A joint over :math:`A` agents with states of size :math:`S` is an
:math:`(AS, AS)` matrix whose block :math:`(a, b)` belongs to agents
:math:`a` and :math:`b`; anchors are known and hold no block."""
from typing import List, NamedTuple, Optional, Sequence, Tuple

import torch
from torch import Tensor
from torch_geometric.data import Batch

from tg_nebp.utils import free_memory_bytes, inputs, symmetrize

__all__ = ['GraphLayout', 'graph_index', 'check_dense_joint',
           'check_predicted_prior', 'predict_joint', 'range_blocks',
           'add_link_information', 'marginal_blocks', 'block_diagonal',
           'unit_vectors', 'scope_index', 'WoodburyPrior', 'WoodburyUpdate',
           'JOINT_COPIES', 'bounded_inflation', 'bounded_inflation_map',
           'joint_cross', 'joined_joint',
           'rts_backward', 'rts_backward_chain']

#: Dense :math:`(AS, AS)` float64 matrices alive at once in a joint
#: recursion (covariance, information, factor, temporaries), for the
#: memory estimate of :func:`check_dense_joint`.
JOINT_COPIES = 6


def graph_index(data) -> Tensor:
    r"""The graph of every node :math:`(N)` of a single (all zero) or
    batched realization."""
    if isinstance(data, Batch):
        return data.batch
    return torch.zeros(data.num_nodes, dtype=torch.long,
                       device=data.anchor.device)


class GraphLayout(NamedTuple):
    r"""Where the agents of each graph of a (batched) realization are:
    their node indices per graph, and every node's index among its graph's
    agents (:math:`-1` for anchors)."""
    agents: List[Tensor]
    agent_index: Tensor
    graph_of: Tensor

    @classmethod
    def of(cls, data) -> 'GraphLayout':
        r"""The layout of :obj:`data`, a single or batched realization."""
        graph_of = graph_index(data)
        return cls.of_nodes(data.anchor, graph_of, int(graph_of.max()) + 1
                            if data.num_nodes else 0)

    @classmethod
    def of_nodes(cls, anchor: Tensor, graph_of: Optional[Tensor] = None,
                 num_graphs: int = 1) -> 'GraphLayout':
        r"""The layout of nodes with the anchor mask :obj:`anchor`
        :math:`(N)` in the graphs :obj:`graph_of` :math:`(N)` of
        :obj:`num_graphs` (one graph by default)."""
        if graph_of is None:
            graph_of = torch.zeros_like(anchor, dtype=torch.long)
        agents, agent_index = [], torch.full_like(graph_of, -1)
        for g in range(num_graphs):
            nodes = ((graph_of == g) & ~anchor).nonzero().view(-1)
            agent_index[nodes] = torch.arange(nodes.numel(),
                                              device=nodes.device)
            agents.append(nodes)
        return cls(agents, agent_index, graph_of)


def check_dense_joint(num_agents: int, state_dim: int, what: str,
                      device='cpu', free: Optional[int] = None) -> None:
    r"""Refuses, with a :class:`ValueError` naming the sizes, a joint over
    :obj:`num_agents` agents whose :obj:`JOINT_COPIES` dense float64
    matrices do not fit in the free memory of :obj:`device` (or
    :obj:`free` bytes), before any work starts."""
    size = num_agents * state_dim
    needed = JOINT_COPIES * size * size * 8
    free = free_memory_bytes(str(device)) if free is None else free
    if needed > free:
        fits = int((free / (JOINT_COPIES * 8))**0.5) // state_dim
        raise ValueError(
            f"{what} of a graph of {num_agents} agents needs dense {size} x "
            f"{size} float64 matrices, about {needed / 2**30:.3g} GiB in "
            f"all, but {free / 2**30:.3g} GiB are free on {device}: it runs "
            f"up to about {fits} agents per graph here")


def check_predicted_prior(data, motion, what: str,
                          use_control: bool = True) -> None:
    r"""Refuses, with a :class:`ValueError` naming :obj:`prior_cov` and the
    agent, a prior whose prediction through the motion model,
    :math:`\mathbf{F} \boldsymbol{\Sigma}_0 \mathbf{F}^\top + \mathbf{Q}`,
    has no float64 Cholesky factor: the first covariance that a Gaussian
    method (:obj:`what`) inverts. A zero prior variance is fine where the
    motion model's noise reaches it (a velocity known at the start); an
    agent whose whole state is known is an anchor."""
    agents = ~data.anchor
    mean = data.prior_mean[agents].double()
    # the first step's inputs where the method reads them (the prediction
    # it makes first)
    control = getattr(data, 'control', None)
    given = inputs(None if control is None or not use_control else
                   control[agents, 0].double())
    _, jacobian, noise = motion.linearize(mean, **given)
    predicted = (jacobian @ data.prior_cov[agents].double() @
                 jacobian.transpose(-1, -2) + noise)
    _, failed = torch.linalg.cholesky_ex(predicted)
    if bool(failed.any()):
        first = int(failed.nonzero()[0, 0])
        node = int(agents.nonzero()[first, 0])
        eig = torch.linalg.eigvalsh(predicted[first])
        raise ValueError(
            f"'prior_cov[{node}]' of agent {node} is singular where the "
            f"motion model {motion} adds no noise (predicted eigenvalues "
            f"{[float(f'{e:.3g}') for e in eig]}): {what} needs a "
            f"positive predicted variance in every direction (a known state "
            f"is an anchor's)")


def bounded_inflation(cov: Tensor, predicted: Tensor,
                      kappa: Tensor) -> Tensor:
    r"""The covariances :obj:`cov` :math:`(N, S, S)` of beliefs after a
    step's links inflated by :obj:`kappa` :math:`(N)`, never beyond the
    same step's prediction :obj:`predicted` :math:`(N, S, S)` (before the
    links): in every direction the inflation undoes at most what the links
    took away.

    With :math:`\boldsymbol{\Sigma} = \mathbf{L} \mathbf{L}^\top` and
    the generalized eigenvalues :math:`\mathbf{L}^{-1} \mathbf{P}
    \mathbf{L}^{-\top} = \mathbf{U} \boldsymbol{\Lambda}
    \mathbf{U}^\top` (:math:`\lambda \geq 1` where the links brought
    information),

    .. math::
        \boldsymbol{\Sigma}' = \mathbf{L} \mathbf{U}
        \operatorname{diag}\big(\min(\kappa, \max(\lambda, 1))\big)
        \mathbf{U}^\top \mathbf{L}^\top,

    which is :math:`\kappa \boldsymbol{\Sigma}` where every direction's
    variance was reduced at least :math:`\kappa` times, and leaves a
    direction that no link measured as it is (:obj:`cov` of a
    condition number beyond :math:`\epsilon^{-1/2}` of its dtype counts
    as one without a Cholesky factor, below). A global inflation
    :math:`\kappa \boldsymbol{\Sigma}` compensates the information that a
    filter of marginals counts again (shared through links); applied to a
    direction that got none, it compounds with every step: a robot seeing
    one range a step had its sideways variance grow as :math:`\kappa^t`
    (above :math:`10^6` m² on a real sequence). A :obj:`kappa` at most 1
    deflates as given; a :obj:`cov` without a Cholesky factor (an anchor's
    zero) is scaled by :obj:`kappa` as it is."""
    kappa = kappa.to(cov).view(-1, 1)
    if not kappa.requires_grad and bool((kappa == 1).all()):
        return cov  # nothing inflated (plain Gaussian BP)
    ok, safe, eigvecs, factor = _inflation_factors(cov, predicted, kappa)
    root = safe @ eigvecs
    # what is added to cov: exactly zero where nothing is inflated (an
    # untrained learned inflation of 1 is plain Gaussian BP bit for bit)
    added = ((root * (factor - 1).unsqueeze(-2)) @ root.transpose(-1, -2))
    added = symmetrize(added)
    return torch.where(ok.view(-1, 1, 1), cov + added,
                       kappa.view(-1, 1, 1) * cov)


def bounded_inflation_map(cov: Tensor, predicted: Tensor,
                          kappa: Tensor) -> Tensor:
    r"""The linear maps :math:`\mathbf{A}` :math:`(N, S, S)` that inflate
    a cloud of covariance :obj:`cov` about its mean as
    :func:`bounded_inflation` inflates the covariance,
    :math:`\mathbf{A} oldsymbol{\Sigma} \mathbf{A}^	op =
    oldsymbol{\Sigma}'`: :math:`\mathbf{A} = \mathbf{L} \mathbf{U}
    \operatorname{diag}(\sqrt{f}) \mathbf{U}^	op \mathbf{L}^{-1}`. A
    particle belief moved by it keeps its shape (its modes, their
    weights) and widens where the links narrowed it. The identity where
    :obj:`cov` has no Cholesky factor (an anchor's zero, a cloud
    collapsed onto a point)."""
    kappa = kappa.to(cov).view(-1, 1)
    ok, safe, eigvecs, factor = _inflation_factors(cov, predicted, kappa)
    eye = torch.eye(cov.size(-1), dtype=cov.dtype, device=cov.device)
    scaled = (safe @ eigvecs) * factor.sqrt().unsqueeze(-2)
    inverse_root = torch.linalg.solve_triangular(safe, eye.expand_as(safe),
                                                 upper=False)
    mapped = scaled @ eigvecs.transpose(-1, -2) @ inverse_root
    return torch.where(ok.view(-1, 1, 1), mapped, eye)


def _inflation_factors(cov: Tensor, predicted: Tensor, kappa: Tensor):
    # the Cholesky factors L of cov (where it has one: 'ok'; an identity
    # elsewhere), the eigenvectors U of L^-1 P L^-T and the factors
    # min(kappa, max(lambda, 1)) of every direction. A factor whose
    # diagonal spans more than half the digits of the dtype (a particle
    # cloud collapsed onto a line) would whiten P beyond what eigh solves:
    # such a covariance counts as one without a factor
    lower, failed = torch.linalg.cholesky_ex(cov)
    diagonal = lower.diagonal(dim1=-2, dim2=-1).abs()
    ok = (failed == 0) & (diagonal.amin(-1) > diagonal.amax(-1) *
                          torch.finfo(cov.dtype).eps**0.25)
    eye = torch.eye(cov.size(-1), dtype=cov.dtype, device=cov.device)
    safe = torch.where(ok.view(-1, 1, 1), lower, eye)
    half = torch.linalg.solve_triangular(safe, predicted, upper=False)
    whitened = torch.linalg.solve_triangular(safe, half.transpose(-1, -2),
                                             upper=False)
    # a factor of subnormal entries (a cloud collapsed onto one particle)
    # passes the spread test and whitens P beyond the dtype's range
    ok = ok & torch.isfinite(whitened).flatten(1).all(1)
    safe = torch.where(ok.view(-1, 1, 1), safe, eye)
    whitened = torch.where(ok.view(-1, 1, 1), whitened, predicted)
    eigvals, eigvecs = torch.linalg.eigh(symmetrize(whitened))
    return ok, safe, eigvecs, torch.minimum(kappa, eigvals.clamp_min(1.0))


def joined_joint(joint: Tensor, new: Tensor, state_dim: int,
                 what: str) -> Tensor:
    r"""The joint covariance of the agents of :obj:`joint` :math:`(AS,
    AS)` followed by those of :obj:`new` :math:`(BS, BS)` (agents joining
    a live session), with no correlation between them; a joint too large
    for the free memory of its device is refused for :obj:`what`
    (:func:`check_dense_joint`)."""
    check_dense_joint((joint.size(0) + new.size(0)) // state_dim, state_dim,
                      what, joint.device)
    extended = joint.new_zeros(joint.size(0) + new.size(0),
                               joint.size(1) + new.size(1))
    extended[:joint.size(0), :joint.size(1)] = joint
    extended[joint.size(0):, joint.size(1):] = new
    return extended


def block_diagonal(blocks: Tensor) -> Tensor:
    r"""The :math:`(AS, AS)` matrix with the blocks :math:`(A, S, S)` on
    its diagonal."""
    count, size = blocks.size(0), blocks.size(-1)
    out = blocks.new_zeros(count, size, count, size)
    index = torch.arange(count, device=blocks.device)
    out[index, :, index, :] = blocks
    return out.view(count * size, count * size)


def marginal_blocks(joint: Tensor, state_dim: int) -> Tensor:
    r"""The diagonal blocks :math:`(A, S, S)` of a joint :math:`(AS, AS)`:
    every agent's marginal covariance (or information)."""
    count = joint.size(0) // state_dim
    index = torch.arange(count, device=joint.device)
    return joint.view(count, state_dim, count,
                      state_dim)[index, :, index, :]


def predict_joint(cov: Tensor, jacobian: Tensor, noise: Tensor) -> Tensor:
    r""":math:`\mathbf{F} \mathbf{P} \mathbf{F}^\top + \mathbf{Q}` for a
    joint covariance :math:`\mathbf{P}` :math:`(AS, AS)` and per-agent
    Jacobians :math:`\mathbf{F}` and noise covariances :math:`\mathbf{Q}`
    :math:`(A, S, S)` (block-diagonal: agents move independently),
    symmetrized."""
    count, size = jacobian.shape[:2]
    blocks = cov.view(count, size, count, size)
    moved = torch.einsum('aij,ajbk,blk->aibl', jacobian, blocks, jacobian)
    index = torch.arange(count, device=cov.device)
    moved[index, :, index, :] += noise
    moved = moved.reshape(count * size, count * size)
    return 0.5 * (moved + moved.transpose(0, 1))


def joint_cross(cov: Tensor, jacobian: Tensor) -> Tensor:
    r""":math:`\mathbf{P} \mathbf{F}^\top` :math:`(AS, AS)` for a joint
    covariance :math:`\mathbf{P}` and per-agent Jacobians
    :math:`\mathbf{F}` :math:`(A, S, S)` (block-diagonal): the
    covariance between the joint state and its prediction, which a
    smoother's backward pass reads (:func:`rts_backward`)."""
    count, size = jacobian.shape[:2]
    blocks = cov.view(count, size, count, size)
    return torch.einsum('aibk,blk->aibl', blocks, jacobian).reshape(
        count * size, count * size)


def rts_backward(filtered_cov: Tensor, cross: Tensor, predicted_cov: Tensor,
                 smoothed_cov: Tensor, filtered_mean: Optional[Tensor] = None,
                 predicted_mean: Optional[Tensor] = None,
                 smoothed_mean: Optional[Tensor] = None
                 ) -> Tuple[Optional[Tensor], Tensor]:
    r"""One step of the Rauch-Tung-Striebel backward pass of `"Maximum
    Likelihood Estimates of Linear Dynamic Systems"
    <https://doi.org/10.2514/3.3166>`_ (Rauch, Tung and Striebel, AIAA J.
    1965): the smoothed Gaussian of step :math:`k` from its filtered one
    (:obj:`filtered_mean`, :obj:`filtered_cov`
    :math:`\mathbf{P}_k`), the prediction of step :math:`k + 1` from it
    (:obj:`predicted_mean` :math:`\boldsymbol{\mu}^-_{k+1}`,
    :obj:`predicted_cov` :math:`\mathbf{P}^-_{k+1}`), their covariance
    :obj:`cross` :math:`\mathbf{P}_k \mathbf{F}_{k+1}^\top` and the
    smoothed Gaussian of step :math:`k + 1`:

    .. math::
        \mathbf{G} = \mathbf{P}_k \mathbf{F}^\top
        (\mathbf{P}^-_{k+1})^{-1}, \quad
        \boldsymbol{\mu}^s_k = \boldsymbol{\mu}_k + \mathbf{G}
        (\boldsymbol{\mu}^s_{k+1} - \boldsymbol{\mu}^-_{k+1}), \quad
        \mathbf{P}^s_k = \mathbf{P}_k + \mathbf{G} (\mathbf{P}^s_{k+1} -
        \mathbf{P}^-_{k+1}) \mathbf{G}^\top.

    Covariance form, so a singular driving noise (the constant-velocity
    models', a robot's odometry) is fine as long as the prediction is
    not. Batched over leading dimensions (a joint :math:`(n, n)` or many
    small ones :math:`(*, n, n)`); the means are optional (a bound has
    none). Returns the smoothed mean (or :obj:`None`) and covariance,
    symmetrized."""
    # G^T = P^-^{-1} F P: one solve with the prediction's Cholesky factor
    factor = torch.linalg.cholesky(predicted_cov)
    gain = torch.cholesky_solve(cross.transpose(-1, -2),
                                factor).transpose(-1, -2)
    cov = filtered_cov + gain @ (smoothed_cov - predicted_cov) @ \
        gain.transpose(-1, -2)
    cov = symmetrize(cov)
    if filtered_mean is None:
        return None, cov
    mean = filtered_mean + (gain @ (smoothed_mean - predicted_mean)
                            .unsqueeze(-1)).squeeze(-1)
    return mean, cov


def rts_backward_chain(filtered_mean: Tensor, filtered_cov: Tensor,
                       predicted_mean: Tensor, predicted_cov: Tensor,
                       cross: Tensor, smoothed_mean: Tensor,
                       smoothed_cov: Tensor) -> Tuple[Tensor, Tensor]:
    r"""The Rauch-Tung-Striebel backward pass (:func:`rts_backward`) over
    a whole chain of :math:`K` steps at once, from the smoothed Gaussian of
    the step after its last (:obj:`smoothed_mean` :math:`(*, n)`,
    :obj:`smoothed_cov` :math:`(*, n, n)`): every step's filtered Gaussian
    (:obj:`filtered_mean` :math:`(*, K, n)`, :obj:`filtered_cov`
    :math:`(*, K, n, n)`), the prediction of the step after it from it
    (:obj:`predicted_mean`, :obj:`predicted_cov`) and their covariance
    :obj:`cross` (:math:`\mathbf{P}_k \mathbf{F}^\top`). Each step is an
    affine map of the next step's smoothed Gaussian,

    .. math::
        \boldsymbol{\mu}^s_k = \mathbf{a}_k + \mathbf{G}_k
        \boldsymbol{\mu}^s_{k+1}, \quad \mathbf{P}^s_k = \mathbf{B}_k +
        \mathbf{G}_k \mathbf{P}^s_{k+1} \mathbf{G}_k^\top,

    with :math:`\mathbf{a}_k = \boldsymbol{\mu}_k - \mathbf{G}_k
    \boldsymbol{\mu}^-_{k+1}` and :math:`\mathbf{B}_k = \mathbf{P}_k -
    \mathbf{G}_k \mathbf{P}^-_{k+1} \mathbf{G}_k^\top`; the maps compose
    associatively, so every step's composition with all after it takes
    :math:`\lceil \log_2 K \rceil` batched rounds (a parallel prefix, as
    the temporal parallelization of `"Temporal Parallelization of Bayesian
    Smoothers" <https://arxiv.org/abs/1905.13002>`_, Särkkä and
    García-Fernández, IEEE TAC 2021) instead of :math:`K` sequential
    steps. Returns the smoothed means :math:`(*, K, n)` and covariances
    :math:`(*, K, n, n)`, symmetrized."""
    gain = torch.cholesky_solve(cross.transpose(-1, -2),
                                torch.linalg.cholesky(predicted_cov)
                                ).transpose(-1, -2)
    offset = filtered_mean - (gain @ predicted_mean.unsqueeze(-1)).squeeze(-1)
    spread = filtered_cov - gain @ predicted_cov @ gain.transpose(-1, -2)
    count, reach = gain.size(-3), 1
    while reach < count:
        # step k composed with the maps of steps k + 1, ..., k + 2 reach - 1
        first, then = slice(None, count - reach), slice(reach, None)
        head = gain[..., first, :, :]
        offset = torch.cat([offset[..., first, :] + (
            head @ offset[..., then, :].unsqueeze(-1)).squeeze(-1),
            offset[..., count - reach:, :]], -2)
        spread = torch.cat([spread[..., first, :, :] + head @ spread[
            ..., then, :, :] @ head.transpose(-1, -2),
            spread[..., count - reach:, :, :]], -3)
        gain = torch.cat([head @ gain[..., then, :, :],
                          gain[..., count - reach:, :, :]], -3)
        reach *= 2
    mean = offset + (gain @ smoothed_mean.unsqueeze(-2).unsqueeze(
        -1)).squeeze(-1)
    cov = spread + gain @ smoothed_cov.unsqueeze(-3) @ gain.transpose(-1, -2)
    return mean, symmetrize(cov)


def unit_vectors(diff: Tensor) -> Tuple[Tensor, Tensor]:
    r"""The lengths :math:`(E)` of the vectors :obj:`diff` :math:`(E, P)`
    and their directions :math:`(E, P)` (zero for a zero vector, where a
    distance has no gradient)."""
    lengths = torch.linalg.vector_norm(diff, dim=-1)
    safe = torch.where(lengths > 0, lengths, torch.ones_like(lengths))
    return lengths, diff / safe.unsqueeze(-1)


def range_blocks(unit: Tensor, weights: Tensor, state_dim: int) -> Tensor:
    r"""The information :math:`(E, 2S, 2S)` on :math:`[\mathbf{x}_j;
    \mathbf{x}_i]` of ranges :math:`d = \|\mathbf{p}_j - \mathbf{p}_i\|`
    with precision (or Fisher information) :obj:`weights` :math:`(E)`:
    :math:`w \mathbf{u} \mathbf{u}^\top` on both position blocks and
    :math:`-w \mathbf{u} \mathbf{u}^\top` off the diagonal, for the unit
    vectors :obj:`unit` :math:`(E, P)` between the positions (the gradient
    of :math:`d` is :math:`\mathbf{u}` in :math:`\mathbf{p}_j` and
    :math:`-\mathbf{u}` in :math:`\mathbf{p}_i`)."""
    count, dim = unit.shape
    block = weights.view(-1, 1, 1) * unit.unsqueeze(-1) * unit.unsqueeze(-2)
    out = unit.new_zeros(count, 2, state_dim, 2, state_dim)
    for a in range(2):
        for b in range(2):
            out[:, a, :dim, b, :dim] = block if a == b else -block
    return out.view(count, 2 * state_dim, 2 * state_dim)


def add_link_information(info: Tensor, blocks: Tensor, sender: Tensor,
                         receiver: Tensor) -> Tensor:
    r"""Adds, in place, the information :math:`(E, 2S, 2S)` of measured
    links on the stacked states :math:`[\mathbf{x}_j; \mathbf{x}_i]` of
    their two ends to the joint information :obj:`info` :math:`(AS, AS)`.
    :obj:`sender` and :obj:`receiver` :math:`(E)` are the ends' agent
    indices in the joint, :math:`-1` for an anchor (known: only the other
    end's block is added)."""
    size = blocks.size(-1) // 2
    count = info.size(0) // size
    ends = torch.stack([sender, receiver], 1)  # [E, 2]
    # the four S x S blocks of every link, addressed by their two agents
    parts = blocks.view(-1, 2, size, 2, size).transpose(2, 3)
    rows = ends.view(-1, 2, 1).expand(-1, 2, 2)
    cols = ends.view(-1, 1, 2).expand(-1, 2, 2)
    keep = (rows >= 0) & (cols >= 0)
    # accumulated per block pair (an agent is the end of many links), then
    # laid out as the joint's rows and columns
    pairs = info.new_zeros(count, count, size, size)
    pairs.index_put_((rows[keep], cols[keep]), parts[keep], accumulate=True)
    info += pairs.transpose(1, 2).reshape(count * size, count * size)
    return info


def scope_index(count: int, state_dim: int, scope: Sequence[int],
                device=None) -> Tensor:
    r"""The rows :math:`(AR)` of a joint over :obj:`count` agents with
    states of size :obj:`state_dim` that hold the entries :obj:`scope`
    (:math:`R` of them, a range model's positions) of every agent, agent
    by agent."""
    read = torch.tensor(scope, dtype=torch.long, device=device)
    agents = torch.arange(count, device=device).view(-1, 1)
    return (agents * state_dim + read).view(-1)


class WoodburyPrior(NamedTuple):
    r"""A joint covariance :math:`\mathbf{P}` :math:`(AS, AS)` (:obj:`cov`)
    ready for updates with informations on :math:`K` of its entries
    (:func:`scope_index`: the measured links inform the positions only):
    its columns there :math:`\mathbf{G} = \mathbf{P} \mathbf{E}^\top`
    (:obj:`gain`) and its block there :math:`\mathbf{C} = \mathbf{E}
    \mathbf{P} \mathbf{E}^\top` (:obj:`inner`), shared by every update
    of the same prior (the Gauss-Newton iterations of a step)."""
    cov: Tensor
    gain: Tensor
    inner: Tensor

    @classmethod
    def of(cls, cov: Tensor, index: Tensor) -> 'WoodburyPrior':
        gain = cov[:, index]
        return cls(cov, gain, gain[index])

    def updated(self, info: Tensor) -> 'WoodburyUpdate':
        r"""The update with the information :obj:`info` :math:`(K, K)` on
        the entries (:class:`WoodburyUpdate`)."""
        eye = torch.eye(info.size(0), dtype=info.dtype, device=info.device)
        return WoodburyUpdate(self, info, torch.linalg.lu_factor(
            eye + info @ self.inner))


class WoodburyUpdate(NamedTuple):
    r"""A joint covariance updated with an information :math:`\mathbf{M}`
    :math:`(K, K)` (:obj:`info`) on :math:`K` of its entries
    (:meth:`WoodburyPrior.updated`), by the Woodbury identity

    .. math::
        (\mathbf{P}^{-1} + \mathbf{E}^\top \mathbf{M} \mathbf{E})^{-1} =
        \mathbf{P} - \mathbf{G} (\mathbf{I} + \mathbf{M}
        \mathbf{C})^{-1} \mathbf{M} \mathbf{G}^\top

    (:class:`WoodburyPrior` gives :math:`\mathbf{G}` and
    :math:`\mathbf{C}`): one LU factorization of size :math:`K`
    (:obj:`system`) instead of inverting the :math:`(AS, AS)` prior and
    posterior. :math:`\mathbf{I} + \mathbf{M} \mathbf{C}` is invertible
    for any positive semi-definite :math:`\mathbf{M}` (a singular one:
    agents without links)."""
    prior: WoodburyPrior
    info: Tensor
    system: Tuple[Tensor, Tensor]

    def covariance(self) -> Tensor:
        r"""The updated covariance :math:`(AS, AS)`, symmetrized."""
        gain = self.prior.gain
        weight = torch.linalg.lu_solve(*self.system, self.info)
        weight = 0.5 * (weight + weight.transpose(0, 1))
        out = self.prior.cov - gain @ weight @ gain.transpose(0, 1)
        return 0.5 * (out + out.transpose(0, 1))

    def solve(self, vector: Tensor) -> Tensor:
        r"""The updated covariance times :obj:`vector` :math:`(AS)`, i.e.
        the solution of the updated information's system, without forming
        the covariance."""
        gain = self.prior.gain
        inner = self.info @ (gain.transpose(0, 1) @ vector)
        return self.prior.cov @ vector - gain @ torch.linalg.lu_solve(
            *self.system, inner.view(-1, 1)).view(-1)
