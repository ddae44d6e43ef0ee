r"""The options of a method of
:func:`~tg_nebp.experiments.evaluate.method_tracker` as one record,
:class:`MethodOptions`: made where they are given (the command line's
flags, a call's keywords), checked once against the method, and handed on
whole to the tracker that it builds. Each field names the methods that
take it (:data:`METHOD_OPTIONS` is read from the fields), so a new option
is one field."""
import dataclasses
import os
from typing import Any, Dict, Mapping, Optional, Tuple, Union

from tg_nebp.data.validation import check_positive_int

__all__ = ['METHODS', 'METHOD_OPTIONS', 'WHOLE_SEQUENCE', 'MethodOptions']

#: The methods of :func:`~tg_nebp.experiments.evaluate.method_tracker`, by
#: their :obj:`metrics.json` key stem: particle BP, NEBP from a checkpoint,
#: Gaussian BP, Gaussian NEBP from a checkpoint, hybrid BP (over Gaussian
#: BP, a window of it or a Gaussian NEBP checkpoint), the centralized IEKF
#: and the posterior CRB.
METHODS = ('bp', 'nebp', 'gbp', 'gnebp', 'hybrid', 'iekf', 'pcrb')

#: The value of :obj:`lag` (:obj:`--lag`) that smooths over the whole
#: sequence: the full smoother (:obj:`iekf`) and its bound (:obj:`pcrb`).
WHOLE_SEQUENCE = 'all'


def _option(methods: Tuple[str, ...], default: Any = None):
    # a field of MethodOptions taken by 'methods'
    return dataclasses.field(default=default,
                             metadata=dict(methods=methods))


@dataclasses.dataclass(frozen=True)
class MethodOptions:
    r"""The options of a method (:data:`METHODS`), each left at
    :obj:`None` (a switch: :obj:`False`) for the method's own default; the
    flag of :obj:`tg-nebp evaluate` and :obj:`track` is :obj:`--` and the
    name with hyphens. See
    :func:`~tg_nebp.experiments.evaluate.method_tracker` for what each
    does. :meth:`check` refuses an option that the method does not take
    (rather than ignore it), a count below one and contradictory
    options."""
    #: A likelihood name instead of the scenario's own.
    measurement: Optional[str] = _option(('bp', 'iekf', 'gbp', 'hybrid',
                                          'pcrb'))
    #: Particles per agent.
    particles: Optional[int] = _option(('bp', 'nebp', 'hybrid'))
    #: Message passing (or Gauss-Newton) iterations per step.
    iterations: Optional[int] = _option(('bp', 'iekf', 'gbp', 'gnebp',
                                         'hybrid'))
    #: Samples of a marginalized message (a count or :obj:`"all"`).
    samples: Union[int, str, None] = _option(('bp', 'nebp'))
    #: The resampler's name.
    resampler: Optional[str] = _option(('bp', ))
    #: The regularization bandwidth (a number or :obj:`"auto"`).
    regularize: Union[float, str, None] = _option(('bp', ))
    #: The effective sample size below which to resample.
    ess_threshold: Optional[float] = _option(('bp', ))
    #: Which ends of a link its range informs.
    ends: Optional[str] = _option(('bp', 'gbp'))
    #: The IEKF keeps only every agent's marginal between steps.
    marginal: bool = _option(('iekf', ), False)
    #: Gaussian BP's covariance inflation.
    inflation: Optional[float] = _option(('gbp', 'hybrid'))
    #: The inflation of the covariance that Gaussian BP or particle BP
    #: reports.
    report_inflation: Optional[float] = _option(('bp', 'gbp', 'hybrid'))
    #: Every agent's measurement noise scale estimated from its links'
    #: innovations (:class:`~tg_nebp.filters.NoiseAdaptation`).
    adapt_noise: bool = _option(('gbp', 'hybrid'), False)
    #: The largest move of a converged iteration; 0 runs every iteration.
    tolerance: Optional[float] = _option(('gbp', 'gnebp', 'hybrid'))
    #: A learned method's checkpoint (a path or a shipped name).
    checkpoint: Union[str, os.PathLike, None] = _option(('nebp', 'gnebp', 'hybrid'))
    #: Compile the message passing.
    compile: bool = _option(('bp', 'nebp', 'gbp'), False)
    #: Ignore the data's known inputs (odometry).
    no_control: bool = _option(METHODS, False)
    #: A window of that many steps, or :data:`WHOLE_SEQUENCE`.
    lag: Union[int, str, None] = _option(('gbp', 'hybrid', 'iekf', 'pcrb'))
    #: The incremental smoother of the whole sequence.
    incremental: bool = _option(('iekf', ), False)
    #: The full smoother started from the incremental smoother's last step
    #: and from a window's smoothed estimates (the better optimum kept),
    #: with the search of every agent's trajectory for a better basin.
    escape: bool = _option(('iekf', ), False)

    @classmethod
    def of(cls, given: Union[Mapping[str, Any], Any]) -> 'MethodOptions':
        r"""The options of a mapping (keywords) or of an object that has
        them as attributes (the command line's parsed arguments); an
        unknown name in a mapping is a :class:`ValueError`."""
        names = [field.name for field in dataclasses.fields(cls)]
        if isinstance(given, Mapping):
            unknown = sorted(set(given) - set(names))
            if unknown:
                raise ValueError(f"unknown method option(s) {unknown}: the "
                                 f"options are {names}")
            return cls(**given)
        return cls(**{name: getattr(given, name) for name in names})

    def given(self) -> Dict[str, Any]:
        r"""The options given: not :obj:`None` (a switch: not
        :obj:`False`)."""
        return {name: value for name, value in
                dataclasses.asdict(self).items()
                if value is not None and value is not False}

    def check(self, method: str) -> 'MethodOptions':
        r"""Itself, checked for :obj:`method`: one it does not take, a
        count below one, a lag that is not a positive count (or, for the
        methods that smooth the whole sequence, :data:`WHOLE_SEQUENCE`)
        and contradictory options are a :class:`ValueError` naming the
        option and its flag."""
        if method not in METHODS:
            raise ValueError(f"method must be one of {', '.join(METHODS)}, "
                             f"got {method!r}")
        for field in dataclasses.fields(self):
            value = getattr(self, field.name)
            # a switch is a bool: 'no' or 'false' switching it on surprises
            if field.default is False and not isinstance(value, bool):
                raise TypeError(f"'{field.name}' (--"
                                f"{field.name.replace('_', '-')}) is a "
                                f"switch: True or False, got {value!r}")
        if self.checkpoint is not None and not isinstance(
                self.checkpoint, (str, os.PathLike)):
            raise TypeError(f"'checkpoint' must be a path or the name of a "
                            f"shipped checkpoint, got {self.checkpoint!r}")
        for name in self.given():
            takers = METHOD_OPTIONS[name]
            if method not in takers:
                raise ValueError(f"'{name}' (--{name.replace('_', '-')}) is "
                                 f"for method {' or '.join(takers)}, not "
                                 f"{method}")
        # here, not in the trackers: NEBP's checkpoint loader reports a
        # constructor's TypeError as a checkpoint that does not match
        for name in ('particles', 'iterations'):
            if getattr(self, name) is not None:
                check_positive_int(getattr(self, name), name)
        if self.samples is not None and self.samples != 'all':
            check_positive_int(self.samples, 'samples')
        lag = self.lag
        if lag == WHOLE_SEQUENCE and method in ('gbp', 'hybrid'):
            raise ValueError(f"'lag' {WHOLE_SEQUENCE!r} (the whole sequence) "
                             f"is for method iekf or pcrb; {method} takes a "
                             f"window of L steps")
        if lag is not None and lag != WHOLE_SEQUENCE:
            check_positive_int(lag, 'lag')
        if self.incremental and lag != WHOLE_SEQUENCE:
            raise ValueError(f"'incremental' is the smoother of the whole "
                             f"sequence: give 'lag' {WHOLE_SEQUENCE!r}")
        if self.escape and (lag != WHOLE_SEQUENCE or self.incremental):
            raise ValueError(f"'escape' (--escape) is the full smoother's "
                             f"search of the whole sequence: give 'lag' "
                             f"{WHOLE_SEQUENCE!r} without 'incremental'")
        if lag is not None and self.report_inflation is not None:
            raise ValueError("'report_inflation' (--report-inflation) and "
                             "'lag': a window reports its beliefs as they "
                             "are")
        if lag is not None and self.adapt_noise:
            raise ValueError("'adapt_noise' (--adapt-noise) and 'lag': the "
                             "noise adaptation runs in the filters, not in "
                             "a window")
        if lag is not None and self.marginal:
            raise ValueError("'lag' and 'marginal': the smoother keeps the "
                             "joint of its window")
        return self


#: Every option of :class:`MethodOptions` and the methods that take it (read
#: from its fields): another method refuses it rather than ignore it.
METHOD_OPTIONS: Dict[str, Tuple[str, ...]] = {
    field.name: field.metadata['methods']
    for field in dataclasses.fields(MethodOptions)}
