r"""Range measurement models: the paper's Gaussian, a heavy-tailed Student-t
and a non-line-of-sight (NLOS) mixture. Each is one :class:`RangeModel`
whose formula lives in its :meth:`log_likelihood_of_distance`; the fast
pieces of :class:`GaussianRange` (in place, closed-form gradient, fused
kernel) are written next to it and gated by :meth:`Model.provides`."""
import math
from typing import Optional, Tuple

import numpy as np
import torch
from scipy.stats import t as student_t
from torch import Tensor

from tg_nebp.data.validation import check_number
from tg_nebp.models.base import LOG_SQRT_2PI, RangeModel, redraw_negative

__all__ = ['GaussianRange', 'StudentTRange', 'NLOSRange',
           'StudentTRangeBySensor']


#: The range noise scales :math:`\sigma` (metres) the range models accept.
SIGMA_RANGE = (1e-6, 1e6)
#: The degrees of freedom that :class:`StudentTRange` accepts.
NU_RANGE = (1.0, 1e6)
#: The ratios of the NLOS bias mean to sigma that :class:`NLOSRange`
#: accepts.
BIAS_RATIO = (1e-6, 1e6)


def _check_sigma(sigma) -> float:
    # the likelihoods scale squared residuals by 1 / (2 sigma^2) in float32:
    # within SIGMA_RANGE (metres) every term stays well inside its range
    sigma = check_number(sigma, 'sigma', maximum=SIGMA_RANGE[1])
    if sigma < SIGMA_RANGE[0]:
        raise ValueError(f"'sigma' must be at least {SIGMA_RANGE[0]:g} m, "
                         f"got {sigma}")
    return sigma


class GaussianRange(RangeModel, name='gaussian'):
    r"""Range measurements with additive Gaussian noise, from the `"Neural
    Enhanced Belief Propagation for Cooperative Localization"
    <https://arxiv.org/abs/2105.12903>`_ paper

    .. math::
        z_{j \to i} = \| \mathbf{p}_j - \mathbf{p}_i \| + r_{j \to i}, \quad
        r_{j \to i} \sim \mathcal{N}(0, \sigma_r^2),

    measured by agent :math:`i` for every node :math:`j` within
    :obj:`max_range`, with log-likelihood

    .. math::
        \log p(z_{j \to i} | \mathbf{x}_j, \mathbf{x}_i) =
        -\frac{(z_{j \to i} - \| \mathbf{p}_j - \mathbf{p}_i \|)^2}
        {2 \sigma_r^2} - \log (\sqrt{2 \pi} \sigma_r).

    A range sensor never reports a negative distance, so sampling redraws
    the noise of the rare measurements that would fall below zero (pairs
    closer than a few :math:`\sigma_r`); the likelihood keeps the paper's
    Gaussian form, defined for any measured range: a negative one (a
    calibrated sensor's, of two close nodes) is accepted. It provides the
    fast pieces of the convolution: an in-place variant, the closed-form
    gradient and the fused-kernel formula.

    Args:
        sigma (float, optional): Noise standard deviation :math:`\sigma_r` in
            metres. (default: :obj:`1.0`)
        max_range (float, optional): Communication range in metres: pairs
            farther apart do not measure. (default: :obj:`20.0`)

    Shapes:
        - **input:** link features :math:`(E, F)` (range first), distances
          :math:`(E, K)`
        - **output:** log-likelihoods :math:`(E, K)`
    """
    def __init__(self, sigma: float = 1.0, max_range: float = 20.0):
        super().__init__(max_range)
        self.sigma = _check_sigma(sigma)

    def params(self) -> dict:
        return dict(sigma=self.sigma, max_range=self.max_range)

    def _log_norm(self) -> float:
        return math.log(math.sqrt(2 * math.pi) * self.sigma)

    def log_likelihood_of_distance(self, z: Tensor,
                                   distances: Tensor) -> Tensor:
        scaled = (z[:, :1] - distances) / self.sigma
        return -0.5 * scaled * scaled - self._log_norm()

    def log_likelihood_of_distance_(self, z: Tensor,
                                    distances: Tensor) -> Tensor:
        r""":meth:`log_likelihood_of_distance` written over
        :obj:`distances` (no autograd): a third of the memory traffic."""
        return distances.sub_(z[:, :1]).square_().mul_(
            -0.5 / self.sigma**2).sub_(self._log_norm())

    def distance_gradient(self, z: Tensor,
                          distances: Tensor) -> Tuple[Tensor, Tensor]:
        r"""The closed-form gradients :math:`(\partial \log p / \partial d,
        \partial \log p / \partial z)` :math:`(E, K)` each, of the
        likelihood with respect to the distance and the range."""
        per_distance = (z[:, :1] - distances) / self.sigma**2
        return per_distance, -per_distance

    def distance_information(self, z: Tensor, distances: Tensor) -> Tensor:
        r"""The closed-form Fisher information :math:`1 / \sigma^2` of a
        range about the distance (see
        :meth:`~tg_nebp.models.RangeModel.range_information`)."""
        return distances.new_full(distances.shape, self.sigma**-2)

    def distance_weights(self, z: Tensor,
                         distances: Tensor) -> Tuple[Tensor, Tensor]:
        r"""The closed-form scores :math:`(z - d) / \sigma^2` and robust
        weights :math:`1 / \sigma^2` (see
        :meth:`~tg_nebp.models.RangeModel.robust_weights`)."""
        score = (z[:, :1] - distances) / self.sigma**2
        return score, torch.full_like(score, self.sigma**-2)

    @staticmethod
    def fused_log_pdf(range_, distance, inv_two_var, log_norm):
        # arithmetic only: compiled into the fused Triton kernel, which
        # reads the range column and the constants of fused_constants()
        residual = range_ - distance
        return -inv_two_var * residual * residual - log_norm

    def fused_constants(self) -> Tuple[float, float]:
        return 0.5 / self.sigma**2, self._log_norm()

    def sample_ranges(self, distances: Tensor, link_state=None,
                      edge_index: Optional[Tensor] = None,
                      generator: Optional[torch.Generator] = None) -> Tensor:
        def noise(shape):
            return self.sigma * torch.randn(shape, dtype=distances.dtype,
                                            device=distances.device,
                                            generator=generator)

        return redraw_negative(noise, distances).view(-1, 1)


class StudentTRange(RangeModel, name='student-t'):
    r"""Range measurements with heavy-tailed Student-t noise, a robust
    likelihood for ranges with outliers (NLOS links, multipath):

    .. math::
        \log p(z | d) = \log \frac{\Gamma(\frac{\nu + 1}{2})}
        {\Gamma(\frac{\nu}{2}) \sqrt{\nu \pi} \sigma}
        - \frac{\nu + 1}{2} \log\Big(1 + \frac{(z - d)^2}{\nu \sigma^2}
        \Big).

    :math:`\nu \to \infty` gives :class:`GaussianRange`; small :math:`\nu`
    lets a range far from the distance cost little, so one bad link does not
    pull an agent away. Sampling redraws negative ranges; the likelihood is
    defined for them, and a measured negative range is accepted.

    Args:
        sigma (float, optional): Scale :math:`\sigma` in metres.
            (default: :obj:`1.0`)
        nu (float, optional): Degrees of freedom :math:`\nu`.
            (default: :obj:`3.0`)
        max_range (float, optional): Communication range in metres.
            (default: :obj:`20.0`)
    """
    def __init__(self, sigma: float = 1.0, nu: float = 3.0,
                 max_range: float = 20.0):
        super().__init__(max_range)
        self.sigma = _check_sigma(sigma)
        nu = check_number(nu, 'nu')
        # below 1 the tails are so heavy that generated ranges overflow;
        # above 1e6 the float32 likelihood rounds away what sets it apart
        # from GaussianRange, which is then the model to use
        if not NU_RANGE[0] <= nu <= NU_RANGE[1]:
            raise ValueError(f"'nu' must lie within [{NU_RANGE[0]:g}, "
                             f"{NU_RANGE[1]:g}] (above, use GaussianRange), "
                             f"got {nu}")
        self.nu = nu

    def params(self) -> dict:
        return dict(sigma=self.sigma, nu=self.nu, max_range=self.max_range)

    def log_likelihood_of_distance(self, z: Tensor,
                                   distances: Tensor) -> Tensor:
        nu = self.nu
        log_norm = (math.lgamma((nu + 1) / 2) - math.lgamma(nu / 2) -
                    0.5 * math.log(nu * math.pi) - math.log(self.sigma))
        scaled = (z[:, :1] - distances) / self.sigma
        return log_norm - 0.5 * (nu + 1) * torch.log1p(scaled * scaled / nu)

    def distance_information(self, z: Tensor, distances: Tensor) -> Tensor:
        r"""The closed-form Fisher information :math:`(\nu + 1) / ((\nu +
        3) \sigma^2)` of a range about the distance (see
        :meth:`~tg_nebp.models.RangeModel.range_information`)."""
        return distances.new_full(distances.shape, (self.nu + 1) / (
            (self.nu + 3) * self.sigma**2))

    def distance_weights(self, z: Tensor,
                         distances: Tensor) -> Tuple[Tensor, Tensor]:
        r"""The closed-form scores :math:`w r` and iteratively reweighted
        least squares weights :math:`w = (\nu + 1) / (\nu \sigma^2 +
        r^2)`, :math:`r = z - d` (see
        :meth:`~tg_nebp.models.RangeModel.robust_weights`)."""
        residual = z[:, :1] - distances
        weights = (self.nu + 1) / (self.nu * self.sigma**2 +
                                   residual * residual)
        return weights * residual, weights

    def sample_ranges(self, distances: Tensor, link_state=None,
                      edge_index: Optional[Tensor] = None,
                      generator: Optional[torch.Generator] = None) -> Tensor:
        def noise(shape):
            # inverse CDF at the generator's uniforms: reproducible draws
            uniform = torch.rand(shape, dtype=torch.float64,
                                 generator=generator).clamp_(1e-300, 1.0)
            quantile = student_t.ppf(uniform.numpy(), self.nu)
            return self.sigma * torch.from_numpy(np.asarray(quantile)).to(
                distances)

        return redraw_negative(noise, distances).view(-1, 1)


class NLOSRange(RangeModel, name='nlos'):
    r"""Ranges with non-line-of-sight (NLOS) links: a link is NLOS with
    probability :math:`p` and then reads long by a positive bias
    :math:`b \sim \mathrm{Exp}(\text{mean } \mu)`:

    .. math::
        z = d + b \, \mathbb{1}_{\mathrm{NLOS}} + r, \quad
        r \sim \mathcal{N}(0, \sigma^2),

    with the mixture likelihood (an exponentially modified Gaussian for the
    NLOS component, :math:`\lambda = 1 / \mu`, :math:`x = z - d`)

    .. math::
        p(z | d) = (1 - p) \, \mathcal{N}(x; 0, \sigma^2) + p \,
        \frac{\lambda}{2} e^{\frac{\lambda}{2} (\lambda \sigma^2 - 2 x)}
        \operatorname{erfc}\Big(\frac{\lambda \sigma^2 - x}{\sqrt{2}
        \sigma}\Big).

    Defined for any measured range: a negative one is accepted.
    Generation draws, at the start of a realization, which node pairs are
    NLOS (the same for both directions), and writes the true flag as a
    second link feature :obj:`"nlos"`, which this likelihood does not read.
    With :obj:`switch_prob` :math:`s > 0` the pairs' states form a
    two-state Markov chain: at every further time step a pair's state is
    redrawn with probability :math:`s` (stationary NLOS probability
    :math:`p`, mean sojourn :math:`1 / (s (1 - p))` steps in LOS). With
    :obj:`oracle=True` the likelihood reads the flag and uses the component
    it names (a bound on what knowing the NLOS links is worth).

    Args:
        sigma (float, optional): LOS noise standard deviation in metres.
            (default: :obj:`1.0`)
        p_nlos (float, optional): Probability :math:`p` that a link is NLOS.
            (default: :obj:`0.2`)
        bias_mean (float, optional): Mean :math:`\mu` of the NLOS bias in
            metres. (default: :obj:`3.0`)
        oracle (bool, optional): Read the true NLOS flag (second link
            feature). (default: :obj:`False`)
        switch_prob (float, optional): Per-step probability :math:`s` that
            a pair's NLOS state is redrawn in generation; :obj:`0` keeps it
            for the whole realization. (default: :obj:`0.0`)
        max_range (float, optional): Communication range in metres.
            (default: :obj:`20.0`)
    """
    generated_features = ('range', 'nlos')

    def __init__(self, sigma: float = 1.0, p_nlos: float = 0.2,
                 bias_mean: float = 3.0, oracle: bool = False,
                 max_range: float = 20.0, switch_prob: float = 0.0):
        super().__init__(max_range)
        self.sigma = _check_sigma(sigma)
        p_nlos = check_number(p_nlos, 'p_nlos', inclusive=True)
        if p_nlos > 1:
            raise ValueError(f"'p_nlos' must lie in [0, 1], got {p_nlos}")
        self.p_nlos = p_nlos
        self.bias_mean = check_number(bias_mean, 'bias_mean')
        # beyond these ratios float32 cannot hold the likelihood's terms
        # (rate sigma overflows, or the NLOS component is a Gaussian)
        ratio = self.bias_mean / self.sigma
        if not BIAS_RATIO[0] <= ratio <= BIAS_RATIO[1]:
            raise ValueError(f"'bias_mean' must lie within "
                             f"[{BIAS_RATIO[0]:g}, {BIAS_RATIO[1]:g}] times "
                             f"'sigma', got {bias_mean} (sigma {sigma})")
        if not isinstance(oracle, bool):
            raise TypeError(f"'oracle' must be a bool, got {oracle!r}")
        self.oracle = oracle
        self.features = ('range', 'nlos') if oracle else ('range', )
        switch_prob = check_number(switch_prob, 'switch_prob', inclusive=True)
        if switch_prob > 1:
            raise ValueError(f"'switch_prob' must lie in [0, 1], got "
                             f"{switch_prob}")
        self.switch_prob = switch_prob

    def params(self) -> dict:
        return dict(sigma=self.sigma, p_nlos=self.p_nlos,
                    bias_mean=self.bias_mean, oracle=self.oracle,
                    max_range=self.max_range, switch_prob=self.switch_prob)

    def log_likelihood_of_distance(self, z: Tensor,
                                   distances: Tensor) -> Tensor:
        sigma, rate = self.sigma, 1.0 / self.bias_mean
        x = z[:, :1] - distances
        scaled = x / sigma
        log_los = -0.5 * scaled * scaled - math.log(sigma) - LOG_SQRT_2PI
        u = (rate * sigma**2 - x) / (math.sqrt(2) * sigma)
        # for u > 0, erfc(u) = erfcx(u) exp(-u^2), and the exponent
        # rate (rate sigma^2 - 2 x) / 2 - u^2 is exactly -x^2 / (2 sigma^2):
        # written so, nothing cancels (the two terms are each about
        # (rate sigma)^2 / 2, which float32 cannot subtract for a small
        # bias). Inputs are clamped to each branch, so neither branch makes
        # an inf or NaN gradient.
        positive, negative = u.clamp_min(0.0), u.clamp_max(0.0)
        log_nlos = math.log(rate / 2) + torch.where(
            u > 0,
            torch.log(torch.special.erfcx(positive)) - 0.5 * scaled * scaled,
            0.5 * rate * (rate * sigma**2 - 2 * x) +
            torch.log(torch.special.erfc(negative)))
        if self.oracle:
            return torch.where(z[:, 1:2] > 0.5, log_nlos, log_los)
        p = self.p_nlos
        if p == 0:
            return log_los
        if p == 1:
            return log_nlos
        return torch.logaddexp(log_los + math.log1p(-p), log_nlos +
                               math.log(p))

    def distance_information(self, z: Tensor, distances: Tensor) -> Tensor:
        r"""The Fisher information of a range about the distance, by
        numerical integration of the squared score of this model's own
        likelihood over the residual (:meth:`information_of_component`);
        with :obj:`oracle`, that of the component each link's flag names
        (see :meth:`~tg_nebp.models.RangeModel.range_information`)."""
        if self.oracle:
            nlos = z[:, 1] > 0.5
            return torch.where(nlos, self.information_of_component(True),
                               self.information_of_component(False)).to(
                                   distances)
        return distances.new_full(distances.shape,
                                  self.information_of_component(None))

    def information_of_component(self, nlos: Optional[bool] = None) -> float:
        r""":math:`\int (\partial \log p(z | d) / \partial d)^2 p(z | d)
        \, dz` of the mixture (:obj:`None`), or, for the oracle, of the
        NLOS (:obj:`True`) or LOS (:obj:`False`) component: the
        likelihood depends on :math:`z - d` alone, so the integral runs over
        the residual, on a grid of steps :math:`\sigma / 100` within
        :math:`12 \sigma` of zero and :math:`\mu / 100` over the bias's
        tail up to :math:`12 \sigma + 60 \mu` (trapezoid rule, float64;
        computed once per model)."""
        cache = self.__dict__.setdefault('_information', {})
        if nlos not in cache:
            sigma, mean = self.sigma, self.bias_mean
            residual = torch.cat([
                torch.linspace(-12 * sigma, 12 * sigma, 2401,
                               dtype=torch.float64),
                torch.linspace(12 * sigma, 12 * sigma + 60 * mean, 6001,
                               dtype=torch.float64)[1:]])
            features = residual.view(-1, 1)
            if self.oracle:
                flag = torch.full_like(features, float(bool(nlos)))
                features = torch.cat([features, flag], 1)
            distance = torch.zeros_like(features[:, :1])
            score = self.distance_score(features, distance).view(-1)
            density = self.log_likelihood_of_distance(features,
                                                      distance).view(-1).exp()
            cache[nlos] = float(torch.trapezoid(score.square() * density,
                                                residual))
        return cache[nlos]

    def sample_links(self, num_nodes: int,
                     generator: Optional[torch.Generator] = None) -> Tensor:
        r"""Which unordered node pairs are NLOS :math:`(N, N)` (symmetric),
        for a whole realization."""
        draw = torch.rand(num_nodes, num_nodes, dtype=torch.float64,
                          generator=generator) < self.p_nlos
        upper = draw.triu(1)
        return upper | upper.t()

    def step_links(self, link_state: Tensor,
                   generator: Optional[torch.Generator] = None) -> Tensor:
        r"""The pairs' NLOS states one time step later: each pair redrawn
        with probability :obj:`switch_prob` (no draw when it is zero)."""
        if self.switch_prob == 0:
            return link_state
        num_nodes = link_state.size(0)
        redraw = torch.rand(num_nodes, num_nodes, dtype=torch.float64,
                            generator=generator) < self.switch_prob
        redraw = (redraw.triu(1) | redraw.triu(1).t())
        fresh = self.sample_links(num_nodes, generator)
        return torch.where(redraw, fresh, link_state)

    def sample_ranges(self, distances: Tensor, link_state: Tensor,
                      edge_index: Tensor,
                      generator: Optional[torch.Generator] = None) -> Tensor:
        nlos = link_state[edge_index[0], edge_index[1]]
        bias = torch.empty_like(distances).exponential_(
            1.0 / self.bias_mean, generator=generator) * nlos

        def noise(shape):
            return self.sigma * torch.randn(shape, dtype=distances.dtype,
                                            device=distances.device,
                                            generator=generator)

        ranges = redraw_negative(noise, distances + bias)
        return torch.stack([ranges, nlos.to(ranges.dtype)], dim=1)


class StudentTRangeBySensor(RangeModel, name='student-t-by-sensor'):
    r"""Ranges from several sensors, each with its own Student-t noise: a
    link's second feature :obj:`"sensor"` names which (0, 1, ...), and its
    likelihood is that sensor's :class:`StudentTRange`,

    .. math::
        \log p(z, k | d) = \log \mathrm{St}\big(z - d; \sigma_k,
        \nu_k\big),

    for real recordings whose links are measured by different means: UWB
    two-way ranges, the known distance between two tags of one rigid body,
    a height sensor read as a range to a point far below (MILUV's, in
    :func:`~tg_nebp.datasets.read_miluv`). Every piece a method needs (the
    Fisher information, the robust weights) is the named sensor's own.

    Args:
        sigma (list): Each sensor's scale :math:`\sigma_k`, metres.
        nu (list): Each sensor's degrees of freedom :math:`\nu_k`.
        max_range (float, optional): Communication range in metres.
            (default: :obj:`20.0`)

    Shapes:
        - **input:** link features :math:`(E, 2)` (range, sensor),
          distances :math:`(E, K)`
        - **output:** log-likelihoods :math:`(E, K)`
    """
    features = ('range', 'sensor')
    generated_features = ('range', 'sensor')

    def __init__(self, sigma=(1.0, ), nu=(3.0, ), max_range: float = 20.0):
        super().__init__(max_range)
        if not isinstance(sigma, (list, tuple)) or not isinstance(
                nu, (list, tuple)) or len(sigma) != len(nu) or not sigma:
            raise ValueError(f"'sigma' and 'nu' must be lists of one entry "
                             f"per sensor, got {sigma!r} and {nu!r}")
        self.sensors = [StudentTRange(s, n, max_range)
                        for s, n in zip(sigma, nu)]

    def params(self) -> dict:
        return dict(sigma=[s.sigma for s in self.sensors],
                    nu=[s.nu for s in self.sensors],
                    max_range=self.max_range)

    def _sensor(self, z: Tensor) -> Tensor:
        # each link's sensor index (E, 1); one the model does not know is
        # refused naming the link
        index = z[:, 1:2].round().long()
        bad = (index < 0) | (index >= len(self.sensors)) | \
            (z[:, 1:2] != index)
        if bool(bad.any()):
            e = int(bad.view(-1).nonzero()[0])
            raise ValueError(f"link {e} names sensor {float(z[e, 1])!r}; "
                             f"the model has sensors 0 to "
                             f"{len(self.sensors) - 1}")
        return index

    def _each(self, z: Tensor, values) -> Tensor:
        # the named sensor's value of every link: values (S, E, ...)
        stacked = torch.stack(values)
        index = self._sensor(z).view((1, -1) + (1, ) * (stacked.dim() - 2))
        return stacked.gather(0, index.expand((1, ) + stacked.shape[1:])
                              ).squeeze(0)

    def log_likelihood_of_distance(self, z: Tensor,
                                   distances: Tensor) -> Tensor:
        return self._each(z, [s.log_likelihood_of_distance(z, distances)
                              for s in self.sensors])

    def distance_information(self, z: Tensor, distances: Tensor) -> Tensor:
        r"""The named sensor's closed-form Fisher information (see
        :meth:`StudentTRange.distance_information`)."""
        return self._each(z, [s.distance_information(z, distances)
                              for s in self.sensors])

    def distance_weights(self, z: Tensor,
                         distances: Tensor) -> Tuple[Tensor, Tensor]:
        r"""The named sensor's closed-form scores and weights (see
        :meth:`StudentTRange.distance_weights`)."""
        pieces = [s.distance_weights(z, distances) for s in self.sensors]
        return (self._each(z, [p[0] for p in pieces]),
                self._each(z, [p[1] for p in pieces]))
