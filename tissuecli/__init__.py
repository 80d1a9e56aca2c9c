"""tissuecli: record, identify and render tissue from a sensorised laparoscopic forceps.

Layers (imports flow downwards only)::

    cli                      the only click importer
    record, fit, play, demo  services
    device, storage, csvio, params   edges: the only pyserial / h5py importers, file formats
    protocol, models, session, synth, clock, units, errors   core numerics and types
"""

__version__ = "0.1.0"
SCHEMA_VERSION = 1
