"""Exceptions raised by jaxcomp: one clear error per bad input."""


class JaxcompError(Exception):
    """Base class of every error jaxcomp raises on purpose."""


class ModelError(JaxcompError, ValueError):
    """A robot model that cannot be used: unknown name, bad file, unsupported joints."""


class InputError(JaxcompError, ValueError):
    """A value passed to jaxcomp that is malformed: wrong shape, NaN, unknown name."""


class FileError(InputError):
    """A file or folder given that cannot be read or written: locked by another run,
    read-only, a full disk, or one that would replace what must be kept."""
