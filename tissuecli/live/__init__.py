"""The live view while recording: a local web page of the force and closure traces,
the force-closure loop of the current grasp, the running estimate and the recording
status, and the same numbers as JSON at ``/api/state`` (docs/usage.md, docs/formats.md).

``state.py`` holds what is shown (the recorder appends to it); ``server.py`` serves it
with the standard library's HTTP server; ``assets/`` is the page, with uPlot (MIT)
vendored so that no request leaves the machine.
"""
