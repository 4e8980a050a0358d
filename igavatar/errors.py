"""Typed errors raised by the library; only the CLI turns them into exit codes.

    raise InputError("poses.npz: key 'rotvecs' has shape (10, 3), expected (N, J, 3)")

Every message names what is wrong, where (file, key, shape) and, when it helps, how to fix it.
"""


class IgavatarError(Exception):
    """Base class of every error a user can cause or fix; the CLI prints it as one line."""

    exit_code = 2


class InputError(IgavatarError):
    """A user-supplied file, directory, key, shape or option is missing or malformed."""


class ArtifactError(IgavatarError):
    """An artifact on disk is missing, of the wrong kind or version, or fails its hashes."""

    exit_code = 3


class BodyModelError(IgavatarError):
    """A body model is unknown, unavailable, or its files are malformed."""


class NotAvailableError(IgavatarError):
    """A feature that this version of igavatar does not implement yet."""

    exit_code = 4


class UnsafeOutputError(InputError):
    """An output path holds something igavatar must not replace (user files, an input, another kind)."""


class StorageError(IgavatarError):
    """The file system refused a write or read: read-only, no permission, no space, path too long."""

    exit_code = 5


class ResourceLimitError(InputError):
    """A size the user chose (resolution, rays, samples, image size) needs more memory than there is."""


class Terminated(KeyboardInterrupt):
    """SIGTERM, raised where Ctrl-C would be so that every stage cleans up (and train checkpoints) alike.

    A KeyboardInterrupt subclass on purpose: code that already handles Ctrl-C handles this too.
    """
