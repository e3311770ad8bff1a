"""Exception types. Every message names the file (and line where there is one) and says what to do."""


class RoadsurfError(Exception):
    """Base class for errors a user can act on."""


class DriveFormatError(RoadsurfError):
    """A drive folder does not follow the drive format (see docs/formats.md)."""


class ConfigError(RoadsurfError):
    """A configuration file has unknown keys or ill-typed values."""


class ModelFileError(RoadsurfError):
    """A classifier model file is missing, corrupt or incompatible."""


class FrameReadError(RoadsurfError):
    """An image could not be decoded (missing, unreadable or truncated). Stages skip the frame."""


class OutputError(RoadsurfError):
    """An output could not be written (disk full, read-only or unwritable folder)."""


class InputError(RoadsurfError):
    """An input file is unreadable (encoding, truncation, bad content) outside the drive format."""


class RunFolderBusyError(OutputError):
    """Another roadsurf run is working in the same output folder."""
