"""The kortex_api namespace the Kortex adapter reads: its names and their import.

``KortexArm`` takes what it uses of Kinova's ``kortex_api`` (transports, router and send
options, session manager, the Base, BaseCyclic and ActuatorConfig clients, the ``*_pb2``
message modules, the two exceptions) as one namespace, its ``api``: ``KORTEX_API`` names them
and the kortex_api module each comes from, ``import_kortex_api`` imports them from an installed
kortex_api (it is not on PyPI), and ``kortex_api_namespace`` makes the namespace of exactly
those names, from kortex_api or from an emulator (``kortex_fake_api``).
"""

from __future__ import annotations

import importlib
from collections.abc import Mapping
from types import SimpleNamespace
from typing import Any

#: What the adapter takes from kortex_api: each name and the kortex_api module it comes from
#: (a class of that module, or the module's submodule of that name: the ``*_pb2`` messages).
KORTEX_API = {
    "TCPTransport": "kortex_api.TCPTransport",
    "UDPTransport": "kortex_api.UDPTransport",
    "RouterClient": "kortex_api.RouterClient",
    "RouterClientSendOptions": "kortex_api.RouterClient",
    "SessionManager": "kortex_api.SessionManager",
    "BaseClient": "kortex_api.autogen.client_stubs.BaseClientRpc",
    "BaseCyclicClient": "kortex_api.autogen.client_stubs.BaseCyclicClientRpc",
    "ActuatorConfigClient": "kortex_api.autogen.client_stubs.ActuatorConfigClientRpc",
    "KServerException": "kortex_api.Exceptions.KServerException",
    "KClientException": "kortex_api.Exceptions.KClientException",
    "Session_pb2": "kortex_api.autogen.messages",
    "Common_pb2": "kortex_api.autogen.messages",
    "Base_pb2": "kortex_api.autogen.messages",
    "BaseCyclic_pb2": "kortex_api.autogen.messages",
    "ActuatorConfig_pb2": "kortex_api.autogen.messages",
}


def kortex_api_namespace(members: Mapping[str, Any]) -> SimpleNamespace:
    """The namespace the adapter reads kortex_api from (``KortexArm``'s ``api``).

    Args:
        members: each name of ``KORTEX_API`` and what stands for it (kortex_api's class or
            message module, or an emulator's).

    Returns:
        A namespace of exactly those names.

    Raises:
        ValueError: a name of ``KORTEX_API`` is missing from ``members``, or one is extra.
    """
    missing, extra = set(KORTEX_API) - set(members), set(members) - set(KORTEX_API)
    if missing or extra:
        raise ValueError(
            f"a kortex_api namespace needs {sorted(KORTEX_API)}: missing {sorted(missing)}, "
            f"extra {sorted(extra)}"
        )
    return SimpleNamespace(**{name: members[name] for name in KORTEX_API})


def _import_member(name: str, module: str) -> Any:
    """``from module import name``: the module's attribute, else its submodule ``name``."""
    found = importlib.import_module(module)
    if hasattr(found, name):
        return getattr(found, name)
    return importlib.import_module(f"{module}.{name}")


def import_kortex_api() -> SimpleNamespace:
    """The kortex_api classes and message modules the adapter uses (lazy import).

    Returns:
        The namespace of ``KORTEX_API``'s names (``kortex_api_namespace``).

    Raises:
        ImportError: kortex_api is not installed (it is not on PyPI: the message says how).
    """
    try:
        members = {name: _import_member(name, module) for name, module in KORTEX_API.items()}
    except ImportError as exc:
        raise ImportError(
            "the Kortex adapter needs Kinova's kortex_api, which is not on PyPI: download "
            "kortex_api-2.6.0.post3-py3-none-any.whl from Kinova and run "
            "'pip install --no-deps kortex_api-2.6.0.post3-py3-none-any.whl "
            '"protobuf==3.20.*"\' (or use KortexArm.emulated() without an arm)'
        ) from exc
    return kortex_api_namespace(members)
