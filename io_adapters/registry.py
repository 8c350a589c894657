"""Adapters by URL scheme, imported only when an endpoint of that scheme is opened.

Built in:

* ``udp://HOST:PORT[?options]`` — :class:`io_adapters.udp.UdpEndpoint`.  HOST:PORT is
  the device's address for both sides: the device binds it, the controller sends
  to it from an ephemeral port and the device takes and answers the one controller
  it has pinned (the first to speak; another after a handshake, once the pinned one
  has been silent for ``takeover_ms``).
* ``serial://PORT[?options]`` — :class:`io_adapters.serial_link.SerialEndpoint`;
  PORT is a device path (``serial:///dev/ttyUSB0``), an open file descriptor
  (``serial://fd/5``) or a pyserial URL (``serial://loop://``); the same pinning
  by session.
* ``can://INTERFACE/CHANNEL?node=N&rated_current_ma=I`` — CANopen CiA 402 through
  python-can: :class:`io_adapters.can_cia402.CanDriveEndpoint` (device) and
  :class:`io_adapters.can_master.CanMasterEndpoint` (controller).

More schemes come from :func:`register` or from installed packages that declare
an entry point in the group ``feeddrive_hil.adapters``, named after the scheme,
whose value is ``"module:Class"`` (an :class:`~io_adapters.base.Endpoint`
subclass).  A built-in scheme cannot be replaced.
"""

import importlib
from importlib.metadata import entry_points

from io_adapters.base import AdapterConfigError, Endpoint, Role

ENTRY_POINT_GROUP = "feeddrive_hil.adapters"
BUILTIN = {
    "udp": "io_adapters.udp:UdpEndpoint",
    "serial": "io_adapters.serial_link:SerialEndpoint",
    "can": "io_adapters.can_cia402:CanDriveEndpoint",
}
_registered: dict[str, str] = {}


def _plugins() -> dict[str, str]:
    return {ep.name: ep.value for ep in entry_points(group=ENTRY_POINT_GROUP)}


def register(scheme: str, target: str) -> None:
    """Make ``scheme://...`` open ``target``, a ``"module:Class"`` string; the module
    is imported only when such an endpoint is opened."""
    if not scheme.isidentifier() or scheme != scheme.lower():
        raise AdapterConfigError(f"scheme {scheme!r}: use a lower-case identifier")
    module, _, cls = target.partition(":")
    if not module or not cls:
        raise AdapterConfigError(f"adapter {target!r} for {scheme!r}: expected 'module:Class'")
    if scheme in BUILTIN or scheme in _registered:
        raise AdapterConfigError(f"scheme {scheme!r} is already registered")
    _registered[scheme] = target


def known_schemes() -> list[str]:
    """Every scheme that :func:`open_endpoint` accepts (nothing is imported)."""
    return sorted({**_plugins(), **_registered, **BUILTIN})


def resolve(scheme: str) -> type[Endpoint]:
    """The endpoint class of ``scheme``, importing its module now."""
    target = BUILTIN.get(scheme) or _registered.get(scheme) or _plugins().get(scheme)
    if target is None:
        raise AdapterConfigError(f"unknown adapter scheme {scheme!r}; known: "
                                 f"{', '.join(known_schemes())}")
    module_name, _, class_name = target.partition(":")
    try:
        cls = getattr(importlib.import_module(module_name), class_name)
    except (ImportError, AttributeError) as e:
        raise AdapterConfigError(f"adapter {target!r} for scheme {scheme!r} cannot be "
                                 f"loaded: {e}") from e
    if not (isinstance(cls, type) and issubclass(cls, Endpoint)):
        raise AdapterConfigError(f"adapter {target!r} for scheme {scheme!r} is not an "
                                 f"Endpoint subclass")
    return cls


def open_endpoint(url: str, role: Role | str) -> Endpoint:
    """Open the ``role`` side ("device" or "controller") of the link at ``url``.
    Raises :class:`~io_adapters.base.AdapterConfigError` for an unknown scheme or a bad
    URL, :class:`~io_adapters.base.AdapterError` if the transport cannot be opened."""
    scheme, sep, _ = url.partition("://")
    if not sep:
        raise AdapterConfigError(f"{url!r} is not a URL (scheme://...); known schemes: "
                                 f"{', '.join(known_schemes())}")
    try:
        role = Role(role)
    except ValueError as e:
        raise AdapterConfigError(f"role {role!r}: expected 'device' or 'controller'") from e
    return resolve(scheme.lower()).from_url(url, role)
