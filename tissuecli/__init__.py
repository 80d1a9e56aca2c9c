"""tissuecli: record, identify and render tissue from a sensorised laparoscopic forceps.

Layers (imports flow downwards only)::

    cli                                   the only click importer
    demo, record, fit, play, transfer, simulate   services (simulate: device firmware)
    report, storage, device, csvio, params   edges: HTML, HDF5 (only h5py importer),
                                          serial (only pyserial importer), CSV, JSON
    identify, bayes, derivatives, display, synth, clock, protocol,
    calibration, models, session, units, errors   numerics and types (no files)
"""

__version__ = "0.1.0"
SCHEMA_VERSION = 1
