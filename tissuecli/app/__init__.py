"""The services the command line calls, one per job: :mod:`~tissuecli.app.record`,
:mod:`~tissuecli.app.fit`, :mod:`~tissuecli.app.play`, :mod:`~tissuecli.app.transfer`
(import and export), :mod:`~tissuecli.app.simulate` and :mod:`~tissuecli.app.demo`.
Each reads and writes files through :mod:`tissuecli.formats`, talks to devices through
:mod:`tissuecli.hw`, and leaves the numerics to :mod:`tissuecli.identify` and
:mod:`tissuecli.render`."""
