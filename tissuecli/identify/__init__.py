"""Identification of the tissue law from a session: numerics only, no files.

- :mod:`~tissuecli.identify.prepare`: the sample grid, holes for lost and clipped samples;
- :mod:`~tissuecli.identify.derivatives`: the differentiators (a registry);
- :mod:`~tissuecli.identify.design`: design matrices and the errors-in-variables correction;
- :mod:`~tissuecli.identify.noise`: residual correlation and the data weight;
- :mod:`~tissuecli.identify.posterior`: the exact posterior and evidence;
- :mod:`~tissuecli.identify.sampling`: emcee and stepping-stone, where no closed form exists;
- :mod:`~tissuecli.identify.bayes`, :mod:`~tissuecli.identify.pinv`: the estimators;
- :mod:`~tissuecli.identify.outcome`: :func:`fit_session`, both estimators in one call.
"""

from .bayes import BayesianFit, ModelResult
from .forms import parse_forms
from .outcome import FitOutcome, fit_session
from .pinv import WindowedPinv

__all__ = ["BayesianFit", "FitOutcome", "ModelResult", "WindowedPinv", "fit_session", "parse_forms"]
