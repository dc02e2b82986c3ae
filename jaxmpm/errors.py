"""Exceptions with messages meant for users (the CLI prints them and exits with code 2)."""


class JaxmpmError(Exception):
    """Base class of all errors jaxmpm reports to users."""


class SceneError(JaxmpmError, ValueError):
    """A scene spec is invalid: the message names the key, file or value."""


class ObservationError(JaxmpmError, ValueError):
    """An observation file is missing, malformed or inconsistent with the scene."""


class SimulationError(JaxmpmError, RuntimeError):
    """A simulation became unstable (CFL violated or NaN)."""


class JaxmpmWarning(UserWarning):
    """Something in the input will not do what it says (the CLI prints these as ``warning: ...``)."""
