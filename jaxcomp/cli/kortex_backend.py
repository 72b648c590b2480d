"""Opening the real arm for the commands (``--robot kortex``): one clear error, no traceback."""

from __future__ import annotations

from jaxcomp.errors import JaxcompError


def open_kortex_arm(ip: str, **options):
    """``KortexArm(ip, **options)``; kortex_api missing (the error says what to install) or
    the arm unreachable become a ``JaxcompError`` (the CLI prints one ``error:`` line).

    Args:
        ip: the arm's address.
        **options: ``KortexArm``'s keyword arguments.

    Returns:
        The open ``KortexArm``.

    Raises:
        JaxcompError: kortex_api missing, the arm unreachable, or ``KortexArm``'s own
            (``HardwareFault``).
    """
    from jaxcomp.hardware import KortexArm

    try:
        return KortexArm(ip, **options)
    except JaxcompError:
        raise
    except ImportError as exc:
        raise JaxcompError(str(exc)) from None
    except Exception as exc:  # noqa: BLE001 - transport errors of kortex_api
        raise JaxcompError(f"cannot open the arm at {ip}: {exc}") from None
