"""Serving the viewer's page: which hosts may serve it, whether a port is taken, waiting until stopped."""

from __future__ import annotations

import math
import time
from typing import TYPE_CHECKING, Callable, Optional


from ..errors import InvalidInputError, describe

if TYPE_CHECKING:  # pragma: no cover
    pass


def wait_until_stopped(stopped: Callable[[], bool], duration: Optional[float] = None) -> None:
    """Blocks until ``stopped()`` is true, ``duration`` seconds passed (None: no limit) or Ctrl-C."""
    end = math.inf if duration is None else time.monotonic() + float(duration)
    try:
        while not stopped() and time.monotonic() < end:
            time.sleep(min(0.2, max(end - time.monotonic(), 0.0)))
    except KeyboardInterrupt:
        pass


def check_host(host: str, *, allow_remote: bool = False) -> bool:
    """Checks that the viewer can listen on ``host`` at once (no hang on an address it cannot bind).

    Returns:
        True when ``host`` is a loopback interface (this machine only), False when it serves the
        network (only with ``allow_remote``).

    Raises:
        InvalidInputError: ``host`` is not an IP address or name of this machine (say
            ``999.1.1.1``, or an address of another machine), or is not loopback (``0.0.0.0``,
            a LAN address) without ``allow_remote=True``: the viewer would serve the scene to
            the network.
    """
    import ipaddress
    import socket

    if not isinstance(host, str) or not host or len(host) > 253:
        raise InvalidInputError("host", "an IP address or host name of this machine", describe(host))
    try:
        infos = socket.getaddrinfo(host, None, type=socket.SOCK_STREAM)
    except (socket.gaierror, UnicodeError, OSError) as exc:
        raise InvalidInputError("host", "an IP address or host name of this machine", f"{host!r} ({exc})") from None
    addresses, problem = set(), ""
    for family, _, _, _, sockaddr in infos:  # "localhost" may name ::1 on a machine without IPv6: one is enough
        with socket.socket(family, socket.SOCK_STREAM) as sock:
            try:
                sock.bind((sockaddr[0], 0))
                addresses.add(sockaddr[0])
            except OSError as exc:
                problem = exc.strerror or str(exc)
    if not addresses:
        raise InvalidInputError("host", "an address of this machine to listen on", f"{host!r} ({problem})")
    loopback = all(ipaddress.ip_address(a.split("%")[0]).is_loopback for a in addresses)
    if not loopback and not allow_remote:
        raise InvalidInputError(
            "host",
            "a loopback address such as 127.0.0.1, or allow_remote=True (CLI: --allow-remote) to serve the "
            "scene to every machine that can reach this one",
            host,
        )
    return loopback


def port_taken(host: str, port: int) -> bool:
    """Whether ``port`` on ``host`` is already in use (a listener answers or binding fails)."""
    import socket

    if port == 0:
        return False
    try:
        infos = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM)
    except OSError:
        return False
    family, _, _, _, sockaddr = infos[0]
    with socket.socket(family, socket.SOCK_STREAM) as sock:
        try:
            sock.bind(sockaddr)
        except OSError:
            return True
    return False


def check_duration(duration: Optional[float], argument: str = "duration") -> Optional[float]:
    """A wait in seconds: None (until Ctrl-C) or a number >= 0; `InvalidInputError` naming ``argument`` otherwise."""
    if duration is not None and (
        isinstance(duration, bool) or not isinstance(duration, (int, float)) or math.isnan(duration) or duration < 0
    ):
        raise InvalidInputError(argument, f"seconds >= 0 (or no {argument}: until Ctrl-C)", duration)
    return duration
