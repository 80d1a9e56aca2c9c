"""Simulated devices, first-class: the forceps and the display as firmware behind real
pseudo-terminals (:mod:`~tissuecli.sim.forceps`, :mod:`~tissuecli.sim.display`,
:mod:`~tissuecli.sim.port`), run as processes (:mod:`~tissuecli.sim.process`), and the
synthetic operator, finger, tissue and sensors behind them (:mod:`~tissuecli.sim.synth`,
:mod:`~tissuecli.sim.finger`), which tests and benchmarks draw sessions with known
truth from."""
