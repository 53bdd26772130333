"""Typed errors shared by every stage.

A :class:`UserError` is bad input (a design, a file, a frame): the CLI prints its one-line
message and exits with its ``exit_code``; no traceback.
"""

from __future__ import annotations


class SoftphantomError(Exception):
    """Base of every error softphantom raises on purpose."""

    exit_code = 1


class UserError(SoftphantomError):
    """Bad input from the user; the message names the field, line or byte offset."""

    exit_code = 2


class DesignError(UserError):
    """A design that cannot be built (names the field and the limit)."""


class MeshError(UserError):
    """Meshing failed for a design that passed validation."""


class FileFormatError(UserError):
    """A malformed or truncated file (names the line or byte offset)."""


class SolverError(SoftphantomError):
    """A numerical solve failed (no NaN is ever returned instead)."""

    exit_code = 3
