"""The vocabulary every other layer shares: sessions, tissue laws and their forms,
ADC calibration, device clocks, units and errors. Pure data and numerics (NumPy only);
nothing here touches a file, a port or a plot.

Modules: :mod:`~tissuecli.core.session`, :mod:`~tissuecli.core.forms`,
:mod:`~tissuecli.core.tissue`, :mod:`~tissuecli.core.calibration`,
:mod:`~tissuecli.core.clock`, :mod:`~tissuecli.core.units`, :mod:`~tissuecli.core.errors`.
Nothing is imported here, so ``import tissuecli`` stays cheap for ``--help``.
"""
