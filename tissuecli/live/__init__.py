"""The live view while recording: a local web page of the force and closure traces,
the force-closure loop of the current grasp, the running estimate and the recording
status, and the same numbers as JSON at ``/api/state`` (docs/usage.md, docs/formats.md).

``state.py`` holds what is shown, in memory shared between the recorder (which appends
to it) and the server; ``server.py`` serves it with the standard library's HTTP server
from a process of its own; ``assets/`` is the page, with uPlot (MIT) vendored so that
no request leaves the machine.
"""
