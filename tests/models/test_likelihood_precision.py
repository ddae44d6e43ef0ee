r"""Every range likelihood is accurate to float32 rounding over the whole
range of parameters it accepts and residuals up to 1e6 m: its float32 value
against the same formula in float64 on the same (float32) inputs, drawn by
Hypothesis; and the parameters beyond that range are refused, naming the
parameter."""
import math

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from tg_nebp.models import GaussianRange, NLOSRange, StudentTRange
from tg_nebp.models.measurement import BIAS_RATIO, NU_RANGE, SIGMA_RANGE


def log_uniform(low, high):
    return st.floats(math.log10(low), math.log10(high)).map(
        lambda e: 10.0 ** e)


def models():
    sigma = log_uniform(*SIGMA_RANGE)
    return st.one_of(
        st.builds(GaussianRange, sigma=sigma),
        st.builds(StudentTRange, sigma=sigma, nu=log_uniform(*NU_RANGE)),
        sigma.flatmap(lambda s: st.builds(
            NLOSRange, sigma=st.just(s),
            # inside the bounds by more than the rounding of r * s
            bias_mean=log_uniform(BIAS_RATIO[0] * (1 + 1e-12),
                                  BIAS_RATIO[1] * (1 - 1e-12)).map(
                                      lambda r: r * s),
            p_nlos=st.floats(0.0, 1.0))))


@settings(max_examples=300, deadline=None)
@given(model=models(), scaled=st.lists(st.floats(-60, 60), max_size=8),
       metres=st.lists(st.floats(-1e6, 1e6), max_size=4),
       distance=st.floats(0.0, 100.0))
def test_float32_equals_float64_to_rounding(model, scaled, metres,
                                            distance):
    # residuals in units of the model's scale, and in metres up to 1e6
    sigma = model.sigma
    scale = sigma + getattr(model, 'bias_mean', 0.0)
    residuals = [r * scale for r in scaled] + metres or [0.0]
    d = torch.full((len(residuals), 1), distance, dtype=torch.float32)
    z = d + torch.tensor(residuals, dtype=torch.float32)[:, None]
    single = model.log_likelihood_of_distance(z, d)
    double = model.log_likelihood_of_distance(z.double(), d.double())
    assert single.dtype == torch.float32
    assert torch.isfinite(double).all()
    # float32 rounding of the result and of the terms that make it up
    tolerance = 2e-6 * (1.0 + double.abs()) + 2e-6 * abs(math.log(sigma))
    assert ((single.double() - double).abs() <= tolerance).all(), (
        model, (single.double() - double).abs().max().item())


def test_small_nlos_bias_no_longer_cancels():
    # two terms of about (rate sigma)^2 / 2 = 5e9 used to be subtracted in
    # float32 and gave +510 for a log-likelihood of about -1
    model = NLOSRange(bias_mean=1e-5)
    z, d = torch.tensor([[10.5], [9.0]]), torch.tensor([[10.0], [10.0]])
    single = model.log_likelihood_of_distance(z, d)
    double = model.log_likelihood_of_distance(z.double(), d.double())
    assert torch.allclose(single.double(), double, atol=1e-5)
    assert (double < 0).all()


@pytest.mark.parametrize('make, field', [
    (lambda: StudentTRange(nu=1e300), "'nu' must lie within"),
    (lambda: StudentTRange(nu=1e-300), "'nu' must lie within"),
    (lambda: StudentTRange(nu=0.05), "'nu' must lie within"),
    (lambda: NLOSRange(bias_mean=1e-9), "'bias_mean' must lie within"),
    (lambda: NLOSRange(sigma=2.0, bias_mean=3e6), "'bias_mean' must lie"),
    (lambda: GaussianRange(sigma=1e300), "'sigma' must be at most"),
    (lambda: StudentTRange(sigma=1e-9), "'sigma' must be at least"),
])
def test_parameters_beyond_the_accurate_range_are_refused(make, field):
    with pytest.raises(ValueError, match=field):
        make()
