"""Everything that touches a file: HDF5 sessions and play logs (h5py is imported only
here), parameter, calibration and display profile files, CSV, atomic writes.
docs/formats.md describes every layout.

- :mod:`~tissuecli.formats.hdf5`: attributes, opening, fsync, reading a group;
- :mod:`~tissuecli.formats.writer`: the crash-safe append-only writer;
- :mod:`~tissuecli.formats.space`: free space, room reserved ahead of writes, storage faults;
- :mod:`~tissuecli.formats.sessions`: sessions (write, stream, read, list);
- :mod:`~tissuecli.formats.playlog`: play logs;
- :mod:`~tissuecli.formats.params`: parameter files (their only owner), calibration
  and display profile files;
- :mod:`~tissuecli.formats.csvfile`: CSV sessions;
- :mod:`~tissuecli.formats.jsonfile`, :mod:`~tissuecli.formats.atomic`: JSON and atomic writes.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from .._lazy import lazy_getattr

#: public name -> module: loaded on first use, so reading a JSON file never loads h5py
_EXPORTS = {
    "read_recording": ".recording",
    "write_csv": ".csvfile",
    "Column": ".hdf5",
    "group_names": ".hdf5",
    "read_group": ".hdf5",
    "read_calibration": ".params",
    "read_profile": ".params",
    "read_tissue": ".params",
    "tissue_to_dict": ".params",
    "write_params": ".params",
    "check_new_session": ".sessions",
    "list_sessions": ".sessions",
    "read_session": ".sessions",
    "session_names": ".sessions",
    "session_writer": ".sessions",
    "write_session": ".sessions",
    "SeriesWriter": ".writer",
}

__all__ = [
    "Column",
    "SeriesWriter",
    "check_new_session",
    "group_names",
    "list_sessions",
    "read_calibration",
    "read_recording",
    "read_group",
    "read_profile",
    "read_session",
    "read_tissue",
    "session_names",
    "session_writer",
    "tissue_to_dict",
    "write_csv",
    "write_params",
    "write_session",
]


__getattr__ = lazy_getattr(__name__, _EXPORTS)


if TYPE_CHECKING:
    from .csvfile import write_csv
    from .hdf5 import Column, group_names, read_group
    from .params import read_calibration, read_profile, read_tissue, tissue_to_dict, write_params
    from .recording import read_recording
    from .sessions import (
        check_new_session,
        list_sessions,
        read_session,
        session_names,
        session_writer,
        write_session,
    )
    from .writer import SeriesWriter
