"""Named exceptions. The CLI turns every :class:`TissueError` into a one-line message."""


class TissueError(Exception):
    """Base of every error a user can cause and fix; its message says how."""


class InputError(TissueError):
    """Bad user input: a file, an option or data that cannot be used."""


class DeviceError(TissueError):
    """A serial device could not be opened, or did not answer as the protocol says."""


class DeviceLost(DeviceError):
    """A device vanished mid-session (unplugged, or its process ended)."""


class StorageError(TissueError):
    """An HDF5 file could not be read or written as asked."""


class SessionExists(StorageError):
    """A session of that name is already in the file; sessions are never overwritten."""


class FitError(TissueError):
    """The data cannot identify the model as asked."""


class RenderError(TissueError):
    """The display cannot render the tissue as asked."""
